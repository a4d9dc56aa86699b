"""The compensator for the controller PC: calibrated model -> ONNX graphs -> onnxruntime.

* :mod:`~torchcal.compensate.linalg`: an unrolled, ONNX-exportable solve of small SPD systems;
* :mod:`~torchcal.compensate.chain`: forward kinematics and geometric Jacobian written as a
  fixed graph (no data-dependent control flow);
* :mod:`~torchcal.compensate.compensator`: the compensator and monitor graphs (``torch.nn.Module``);
* :mod:`~torchcal.compensate.export`: ONNX files, manifest and README of a model folder;
* :mod:`~torchcal.compensate.runtime`: the controller-side runner (onnxruntime + numpy only).

Nothing is imported here: the runtime must load on a controller PC without torch.
"""
