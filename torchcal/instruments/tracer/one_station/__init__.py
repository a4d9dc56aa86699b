"""A single length station: one draw-wire (cable) sensor from an unknown anchor to the robot.

``l = |P(q) - A| + c`` with the anchor ``A`` (robot ``base`` frame), the cable attachment point
(the tool point in the ``flange`` frame) and the zero offset ``c`` unknown. Registered as the
instrument ``length_station`` (:mod:`.plugin`). Modules: :mod:`.data` (file ``q1..qN, l1``),
:mod:`.fit` (identification per structure), :mod:`.cv` (random-split and order-blocked
cross-validation, structure choice), :mod:`.commands` (``fit`` / ``evaluate`` handlers and
options) and :mod:`.twin` (``simulate instrument=length_station``).
"""

from torchcal.instruments.tracer.one_station.plugin import LengthStationInstrument

INSTRUMENT = LengthStationInstrument()

__all__ = ["INSTRUMENT", "LengthStationInstrument"]
