"""A single length station: one draw-wire (cable) sensor from an unknown anchor to the robot.

``l = |P(q) - A| + c`` with the anchor ``A`` (robot ``base`` frame), the cable attachment point
(the tool point in the ``flange`` frame) and the zero offset ``c`` unknown. Modules:
:mod:`.data` (file ``q1..qN, l1``), :mod:`.fit` (identification per structure),
:mod:`.cv` (random-split and order-blocked cross-validation, structure choice) and
:mod:`.commands` (``fit`` / ``evaluate`` handlers).
"""
