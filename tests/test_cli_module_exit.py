"""``python -m torchcal.cli`` ends with the status its message gives, also after SIGTERM."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

# Started as ``python -m torchcal.cli simulate``, the instrument lookup first runs source text that
# ends in a caught KeyboardInterrupt (as a library's ``exec`` hit by Ctrl-C would), then the process
# gets SIGTERM: CPython's remembered Ctrl-C must not turn "terminated" (143) into a SIGINT death.
SITECUSTOMIZE = textwrap.dedent("""
    import os, signal, time
    from torchcal.instruments import registry

    _get = registry.get

    def get(name):
        try:
            exec("raise KeyboardInterrupt")
        except KeyboardInterrupt:
            pass
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(10)
        return _get(name)

    registry.get = get
""")


def test_a_terminated_module_run_exits_143_after_a_caught_ctrl_c_in_exec_code(tmp_path):
    (tmp_path / "site").mkdir()
    (tmp_path / "site" / "sitecustomize.py").write_text(SITECUSTOMIZE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path / "site"), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "torchcal.cli", "simulate", "--out", str(tmp_path / "twin")],
                          capture_output=True, text=True, env=env, timeout=120)
    assert "terminated (SIGTERM)" in proc.stderr, proc.stderr
    assert proc.returncode == 143, (proc.returncode, proc.stderr)
    assert not (tmp_path / "twin").exists()


# A command that ends normally: the status, everything printed (through a pipe, so block-buffered),
# an atexit handler and a thread that is not a daemon all finish before the process ends.
ENDING = textwrap.dedent("""
    import atexit, sys, threading, time
    from torchcal import cli

    atexit.register(lambda: print("atexit handler ran", file=sys.stderr, flush=True))

    def late():
        time.sleep(1.5)
        print("thread finished", file=sys.stderr, flush=True)

    threading.Thread(target=late).start()
    sys.stdout.write("the script's output\\n")  # a pipe: block-buffered, so it stays in the buffer
    sys.argv = ["torchcal", *sys.argv[1:]]
    cli.console_main()
""")


def test_the_command_ends_with_its_status_after_flushing_atexit_handlers_and_threads(tmp_path):
    script = tmp_path / "entry.py"
    script.write_text(ENDING)
    buffered = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    proc = subprocess.run([sys.executable, str(script), "evaluate", "--model", str(tmp_path / "none"),
                           "--data", str(tmp_path / "none.csv")], capture_output=True, text=True, timeout=120,
                          env=buffered)
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert proc.stdout == "the script's output\n"
    lines = proc.stderr.splitlines()
    assert lines[0].startswith("torchcal: error:"), proc.stderr
    assert lines[-2:] == ["thread finished", "atexit handler ran"], proc.stderr


# An idle thread pool (its worker threads are not daemons): a normal exit tells it to stop first.
IDLE_POOL = textwrap.dedent("""
    import sys
    from concurrent.futures import ThreadPoolExecutor
    from torchcal import cli

    pool = ThreadPoolExecutor(2)
    pool.submit(print, "pool task ran", file=sys.stderr, flush=True).result()
    sys.argv = ["torchcal", *sys.argv[1:]]
    cli.console_main()
""")


def test_an_idle_thread_pool_does_not_keep_the_command_waiting(tmp_path):
    script = tmp_path / "pool.py"
    script.write_text(IDLE_POOL)
    proc = subprocess.run([sys.executable, str(script), "evaluate", "--model", str(tmp_path / "none"),
                           "--data", str(tmp_path / "none.csv")], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    assert "pool task ran" in proc.stderr
