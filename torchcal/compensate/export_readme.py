"""The integrator's README of an exported folder, written from its manifest (and the stages' own sections)."""

from __future__ import annotations

import math
from collections.abc import Sequence

from torchcal.identify.joint_errors import METADATA_KEYS


def _convergence_text(manifest: dict) -> str:
    """The README's paragraph on what the fixed steps reach, stratum by stratum."""
    conv = manifest["convergence"]
    strata = conv["strata"]
    if conv["task"] == "position":
        what = ("It puts the TCP **position** on the target first and turns the tool toward the nominal orientation only as "
                "far as the position leaves room. Where the position can be held only by turning the wrist (near the wrist "
                "singularity, and near the elbow or shoulder singularity of the arm, where the wrist's lever still moves the "
                "TCP), the tool ends turned from the nominal orientation, at times further than the nominal command turns "
                "it (the last column below); the `residual` output gives the deviation per command. A tool mounted beyond "
                "the TCP then misses by about its length times that angle: export for the production TCP (`--tcp-mm`, "
                "`--tcp-rpy-deg`) so that the point held exactly is the tool's.")
    else:
        what = ("It solves the full 6-D pose; near singular poses the damping keeps the correction small instead of exact, "
                "for the position too.")
    source = manifest["solver"].get("orientation_source")
    oriented = "" if source is None else f" Orientation: {manifest['solver']['orientation_source_note']}."
    lines = [(f"The compensator runs at most {conv['iterations']} Newton steps, each pose until it has converged (task "
              f"`{conv['task']}`). {what} Every step moves a joint by at most "
              f"{manifest['solver']['max_step_rad']:.2f} rad and every iterate stays within the joint limits.{oriented}"), "",
             ("| poses | n | within 1 um | within 1 um where solvable | unsolved p99 / max (mm) | orientation deviation p99 / max (rad) "
              "| turned beyond the nominal command's: > 1 deg, max (deg) |"),
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, s in strata.items():
        if not s.get("n_poses"):
            continue
        solvable = "n/a" if s["solvable_share_within_1um"] is None else f"{100 * s['solvable_share_within_1um']:.1f} % of {s['n_solvable']}"
        lines.append(f"| {name.replace('_', ' ')} | {s['n_poses']} | {100 * s['share_within_1um']:.1f} % | {solvable} | "
                     f"{s['unsolved_tcp_mm']['p99']:.1e} / {s['unsolved_tcp_mm']['max']:.1e} | "
                     f"{s['orientation_deviation_rad']['p99']:.1e} / {s['orientation_deviation_rad']['max']:.1e} | "
                     + (f"{100 * s['share_tool_turn_added_above_1_deg']:.2f} % of poses, "
                        f"{math.degrees(s['tool_turn_added_rad']['max']):.2g} |" if "tool_turn_added_rad" in s else "n/a |"))
    kept = manifest["solver"].get("tool_length_m", 0.0)
    if kept > 0:
        lines += ["", (f"Exported with a tool length of {kept * 1e3:g} mm: the nominal command is sent wherever the corrected "
                       f"one would leave a point {kept * 1e3:g} mm beyond the TCP further off (position error plus that length "
                       "times the tool's orientation deviation, by the model); the `residual` output then gives the nominal "
                       "command's errors.")]
    t = conv["thresholds"]
    lines += ["", (f"Solvable: the position Jacobian's smallest singular value above {t['solvable_above_m_per_rad'] * 1e3:.0f} mm/rad; "
                   f"wrist singular: the last three joints' angular Jacobian below {t['wrist_singular_below']}; position singular: "
                   f"below {t['position_singular_below_m_per_rad'] * 1e3:.0f} mm/rad. Sampling: {conv['sampling']}.")]
    return "\n".join(lines)


def _corrections_text(manifest: dict) -> str:
    """The README's paragraph on how far the compensator turns the joints and the tool, and the limits judged."""
    corrections = manifest.get("corrections") or {}
    limits, extent = corrections.get("limits") or {}, corrections.get("extent") or {}
    lines = ["## Joint corrections", ""]
    for where, e in extent.items():
        lines.append(f"- {where} ({e['n_poses']}): joint correction median {e['median_joint_correction_deg']:.3g} deg, "
                     f"largest {e['largest_joint_correction_deg']:.3g} deg (joint {e['joint']}); tool turned from the nominal "
                     f"orientation median {e['median_tool_rotation_deg']:.3g} deg, largest {e['largest_tool_rotation_deg']:.3g} deg")
    if limits:
        lines += ["", (f"Limits: {limits['median_joint_correction_deg']:g} deg of joint correction and "
                       f"{limits['median_tool_rotation_deg']:g} deg of tool rotation, judged on {limits['judged']}.")]
    if corrections.get("exceeded_but_allowed"):
        lines += ["", "Exceeded and exported anyway (`--allow-large-corrections`): "
                  + "; ".join(corrections["exceeded_but_allowed"]) + "."]
    return "\n".join(lines) if extent or limits else ""


def _expected_line(manifest: dict) -> str:
    expected = manifest.get("expected_accuracy_95")
    if not expected:
        return "Expected accuracy: not calibrated (the model was fitted with `uncertainty=none`)."
    return (f"Expected accuracy: 95 % of TCP position errors below {expected['p95_mm']:.3f} mm at "
            f"{expected['where'].split(';')[0]} ({expected['method']}, {expected['protocol']}).")


def readme_text(manifest: dict, stage_sections: Sequence[str] = ()) -> str:
    """The integrator's README of an exported folder; ``stage_sections``: the stages' own sections
    (:meth:`~torchcal.stages.base.ModelStage.readme_section`), after the files' table."""
    budget = manifest["float32_error_budget"]
    joints = ", ".join(manifest["joint_names"])
    residual = "yes" if manifest["stages"]["residual"] else "no"
    stiffness = "yes" if manifest["stages"]["stiffness"] else "no"
    joint = ", ".join(k.replace("_", " ") for k in METADATA_KEYS.values() if manifest["stages"].get(k)) or "none"
    wrench = manifest.get("wrench")
    n = manifest["n_joints"]
    extra = f", `{wrench['name']}` (batch, 6)" if wrench else ""
    load = "".join(f"\n{section}" for section in stage_sections)
    return f"""# Compensator for {manifest['robot']}

Exported by torchcal {manifest['versions']['torchcal']} (ONNX opset {manifest['opset']}).
Stages: geometry yes, learned residual {residual}, stiffness {stiffness}, joint-space errors {joint}.
{_expected_line(manifest)}

## Files

| file | input | output |
| --- | --- | --- |
| `compensator.onnx` (float64), `compensator_f32.onnx` (float32) | `q_nominal` (batch, {n}), rad{extra} | `q_corrected` (batch, {n}), rad; `residual` (batch, 2): remaining position error, m, and orientation deviation, rad |
| `monitor.onnx` (float64), `monitor_f32.onnx` (float32) | `q` (batch, {n}), rad{extra} | `tcp_error_m` (batch, 3), m, robot base frame |

Joint order: {joints}. Angles in **radians** in and out (convert degrees before the call).
{load}
## Use

Give the compensator the joint command the controller computed with its nominal kinematics; send
the first output to the drives instead. The real robot then puts its TCP where the nominal model
believed it would be, as far as the calibration knows the robot. The second output, `residual`,
says per command how far the model's TCP still is from that target (m: above your tolerance, the
command was not solved, e.g. at a position singularity) and how far the tool is turned from the
nominal orientation (rad).
The monitor graph predicts, for any joint vector, where the real TCP lies relative to the nominal
one (`real - nominal`, m, base frame).

{_convergence_text(manifest)}

{_corrections_text(manifest)}
Runtime: {manifest['runtime']}.

Check `sha256` in `manifest.json` before loading (`torchcal.compensate.runtime.CompensatorRuntime`
does; it needs only onnxruntime and numpy). Run single poses with `intra_op_num_threads=1`.

## Accuracy of float32

Measured at export on {budget['n_poses']} random poses within the joint limits, against the float64
graph: compensated TCP within {budget['compensator_tcp_mm']['max']:.2e} mm (max), monitor within
{budget['monitor_mm']['max']:.2e} mm (max). Use the float64 files where the controller allows it.
"""
