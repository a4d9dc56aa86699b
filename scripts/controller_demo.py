"""Controller-side use of an exported compensator, without torch.

Usage: python scripts/controller_demo.py EXPORT_DIR [--precision float64|float32]

Reads the manifest, corrects a few joint commands in the middle of the joint range, prints the
corrections and the predicted TCP errors, and finally whether torch was imported (it must not
be: a controller PC has onnxruntime and numpy only).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from torchcal.compensate.runtime import CompensatorRuntime


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", help="folder written by 'torchcal export'")
    parser.add_argument("--precision", default="float64", choices=["float64", "float32"])
    args = parser.parse_args(argv)
    runtime = CompensatorRuntime(args.folder, precision=args.precision, threads=1)
    # null: a continuous joint, whose commands here span one turn
    limits = np.array([lim if lim is not None else [-np.pi, np.pi] for lim in runtime.manifest["joint_limits_rad"]])
    rng = np.random.default_rng(0)
    # a few commands within the joint limits (10 % margin), as a controller would send
    span = limits[:, 1] - limits[:, 0]
    q_nominal = limits[:, 0] + span * (0.1 + 0.8 * rng.random((5, runtime.n_joints)))
    q_corrected = runtime.correct(q_nominal)
    error_mm = runtime.predict_error(q_nominal) * 1e3
    print(f"robot {runtime.manifest['robot']}, joints {', '.join(runtime.joint_names)} (rad)")
    for qn, qc, e in zip(q_nominal, q_corrected, error_mm):
        print(
            "correction [mdeg] " + " ".join(f"{v:+8.3f}" for v in np.degrees(qc - qn) * 1e3)
            + "   predicted TCP error [mm] " + " ".join(f"{v:+.3f}" for v in e)
        )
    print(f"torch imported: {'torch' in sys.modules}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
