"""Socket self-calibration: a ball on the flange put into fixed sockets, no measuring instrument.

All configurations of one (placement, socket) group put the ball centre at one unknown point;
two sockets of a placement are a known distance apart (the scale). Modules: :mod:`.data`
(file loading), :mod:`.model` (residuals and Jacobian), :mod:`.fit` (identification),
:mod:`.metrics` (consistency and distortion), :mod:`.twin` (a case with known truth) and
:mod:`.commands` (the ``fit`` / ``evaluate`` handlers).
"""

from torchcal.instruments.sockets.plugin import SocketsInstrument

INSTRUMENT = SocketsInstrument()

__all__ = ["INSTRUMENT", "SocketsInstrument"]
