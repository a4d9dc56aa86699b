"""The collector is frozen at interpreter exit, after the handlers registered later, once."""

from __future__ import annotations

import subprocess
import sys
import textwrap


def _run(code: str) -> str:
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_the_collector_is_frozen_at_exit_and_not_before():
    out = _run("""
        import atexit, gc
        # registered first, so it runs last: it sees the state the interpreter's own collection meets
        atexit.register(lambda: print("at exit", gc.get_freeze_count() > 0, flush=True))
        from torchcal.core.shutdown import skip_collection_at_exit
        skip_collection_at_exit()
        skip_collection_at_exit()
        print("running", gc.get_freeze_count() > 0, flush=True)
        atexit.register(lambda: print("later handler", gc.get_freeze_count() > 0, flush=True))
    """)
    assert out.splitlines() == ["running False", "later handler False", "at exit True"]


def test_registered_once():
    out = _run("""
        import atexit, gc
        calls = []
        gc_freeze = gc.freeze
        gc.freeze = lambda: calls.append(1) or gc_freeze()
        atexit.register(lambda: print(len(calls), flush=True))
        from torchcal.core.shutdown import skip_collection_at_exit
        for _ in range(3):
            skip_collection_at_exit()
    """)
    assert out.splitlines() == ["1"]
