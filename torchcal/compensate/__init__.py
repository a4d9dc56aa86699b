"""The compensator for the controller PC: calibrated model -> ONNX graphs -> onnxruntime.

* :mod:`~torchcal.compensate.linalg`: an unrolled, ONNX-exportable solve of small SPD systems;
* :mod:`~torchcal.compensate.chain`: forward kinematics and geometric Jacobian written as a
  fixed graph (no data-dependent control flow);
* :mod:`~torchcal.compensate.compensator`: the compensator and monitor graphs (``torch.nn.Module``);
* :mod:`~torchcal.compensate.graphs`: the graphs of a model folder built from its stages, and their ONNX bytes;
* :mod:`~torchcal.compensate.export_checks`: the float32 budget and the convergence strata an export measures;
* :mod:`~torchcal.compensate.export`: ONNX files, manifest (and :mod:`~torchcal.compensate.export_readme` its README) of a model folder;
* :mod:`~torchcal.compensate.runtime`: the controller-side runner (onnxruntime + numpy only).

Nothing is imported here: the runtime must load on a controller PC without torch.
"""
