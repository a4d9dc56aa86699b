"""torchcal: differentiable calibration of industrial robots.

Layers (top to bottom): ``data`` (validated measurement tables), ``sim`` (the digital twin),
``kinematics`` (robot models, the differentiable error layer, IK), ``measure`` (instrument
models), ``identify`` (least squares, LM, LASSO, identifiability), ``residual`` (learned
heads), ``compensate`` (the composed compensator and its ONNX export), ``report`` and
``studies``. Internally everything is SI (m, rad) and float64 for identification.
"""

from torchcal.core.errors import DataError, ModelError, TorchcalError

__version__ = "0.1.0"

__all__ = ["DataError", "ModelError", "TorchcalError", "__version__"]
