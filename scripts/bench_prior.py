"""Parameter coverage of the MAP fit against the rank cut, on twins whose truth is known.

``python scripts/bench_prior.py [--poses 120] [--seeds 4]``: for the embedded KR6-like and UR10-like
twins (geometric errors in the fitted parameter set only, so that a parameter's truth exists), the
share of MDH and tool parameters whose truth lies within 1, 2 and 3 posterior sigmas (Gaussian:
68.3 / 95.4 / 99.7 %), for ``prior=tolerance`` at scale 1 and for the rank cut (``prior=none``).
``--full-case DIR`` writes instead a twin case with full link errors (all five MDH+beta entries of
every joint perturbed, as the model's four-per-joint parametrization must absorb) for ``torchcal fit``.
``--compare-selection ROBOT DATA [key=value ...]`` chooses the prior's scale on one measurement file
both ways, by the marginal likelihood (``prior_scale=auto``) and by the grouped cross-validation
(``prior_scale=cv``), and prints both tables and the CPU time of each (the evidence's check).
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from torchcal.identify.calibrate import calibrate
from torchcal.identify.prior import PriorSpec
from torchcal.sim.twin import Twin, TwinConfig

ROBOTS = {"kr6": None, "ur10": str(Path(__file__).resolve().parents[1] / "torchcal/resources/robots/twin-ur10.yaml")}


def in_model_twin(robot: str | None, seed: int, n: int):
    twin = Twin.create(TwinConfig(seed=seed, robot=robot))
    active, nominal = twin.model.default_active(), twin.model.nominal_vector()
    table = twin.model.layout.table_slice
    twin.x_true[table] = torch.where(active[table], twin.x_true[table], nominal[table])
    return twin, twin.sample(n, torch.Generator().manual_seed(seed + 7919))


def coverage(robot: str | None, n: int, seeds: int) -> dict[str, list[float]]:
    z: dict[str, list[float]] = {"prior": [], "rank cut": []}
    for seed in range(seeds):
        twin, train = in_model_twin(robot, seed, n)
        for label, spec in (("prior", PriorSpec()), ("rank cut", None)):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                result = calibrate(twin.robot, train, prior=spec)
            sd = result.covariance.diagonal().sqrt()
            for k, i in enumerate(result.free.tolist()):
                if not result.model.layout.names[i].startswith("base_"):
                    z[label].append(abs(float(result.x[i] - twin.x_true[i])) / float(sd[k]))
    return z


def write_full_case(out: Path, n: int, seed: int, gravity: bool) -> None:
    from torchcal.core.io import atomic_write_json, atomic_write_text
    from torchcal.data.measurements import write_measurements_csv
    from torchcal.kinematics.robot import robot_to_yaml

    config = TwinConfig(seed=seed, n_train=n, gravity=gravity, gear=gravity)
    twin = Twin.create(config)
    gen = torch.Generator().manual_seed(seed + 99)
    layout, nominal = twin.model.layout, twin.model.nominal_vector()
    for i in range(1, twin.robot.dof + 1):
        for field, sigma in (("beta", math.radians(config.angle_error_deg)), ("d", config.length_error_mm * 1e-3)):
            j = layout.index(f"{field}{i}")
            twin.x_true[j] = nominal[j] + float(torch.randn(1, generator=gen, dtype=torch.float64)) * sigma
    gen = torch.Generator().manual_seed(seed + 7919)
    train, test = twin.sample(n, gen), twin.sample(400, gen)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "robot.yaml", robot_to_yaml(twin.robot))
    write_measurements_csv(out / "train.csv", train.q, train.position)
    write_measurements_csv(out / "test.csv", test.q, test.position)
    atomic_write_json(out / "truth.json", twin.truth_dict())


def compare_selection(robot_path: str, data_path: str, overrides: list[str]) -> None:
    """Print the evidence's and the grouped CV's choice of the prior scale on one file."""
    from dataclasses import replace

    from torchcal.config.schema import FitConfig
    from torchcal.data.measurements import load_measurements
    from torchcal.kinematics.robot import load_robot
    from torchcal.stages.geometry import choose_prior, with_tool

    config = FitConfig()
    for item in overrides:
        key, value = item.split("=", 1)
        config = replace(config, **{key: type(getattr(config, key))(value) if getattr(config, key) is not None
                                    else [float(v) for v in value.strip("[]").split(",")]})
    robot = with_tool(load_robot(robot_path), config)
    data = load_measurements(data_path, robot)
    for scale in ("auto", "cv"):
        started = time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            spec, record, _, _ = choose_prior(robot, data, replace(config, prior_scale=scale))
        print(f"prior_scale={scale}: chosen {spec.label()} ({time.process_time() - started:.1f} s CPU)")
        print(f"  {record['protocol']}")
        print("\n".join("  " + line for line in record["table"].splitlines()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=120)
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--full-case", type=Path, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--gravity", action="store_true", help="with --full-case: add gravity compliance and gear errors")
    parser.add_argument("--compare-selection", nargs="+", default=None, metavar="ROBOT DATA [KEY=VALUE]",
                        help="the prior scale chosen by evidence and by grouped CV on one file")
    args = parser.parse_args()
    if args.compare_selection is not None:
        compare_selection(args.compare_selection[0], args.compare_selection[1], args.compare_selection[2:])
        return
    if args.full_case is not None:
        write_full_case(args.full_case, args.poses, args.seed, args.gravity)
        return
    print("| twin | poses x seeds | fit | parameters | within 1 sigma | within 2 sigma | within 3 sigma |")
    print("|---|---|---|---|---|---|---|")
    for name, robot in ROBOTS.items():
        for label, z in coverage(robot, args.poses, args.seeds).items():
            a = np.array(z)
            print(f"| {name} | {args.poses} x {args.seeds} | {label} | {len(a)} | {100 * np.mean(a < 1):.1f} % | "
                  f"{100 * np.mean(a < 2):.1f} % | {100 * np.mean(a < 3):.1f} % |")


if __name__ == "__main__":
    main()
