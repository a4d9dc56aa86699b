"""Refusing a measurement file that belongs to another robot, tool or set-up than a stored model's."""

from __future__ import annotations

import torch

from torchcal.core.errors import DataError
from torchcal.data.measurements import Measurements
from torchcal.stages.store import StoredModel

#: A median error beyond this (mm) on a file means the file is not of this model's robot and set-up.
FOREIGN_FILE_MEDIAN_MM = 25.0


def refuse_foreign_file(errors: torch.Tensor, stored: StoredModel, data: Measurements, register: bool,
                        refused: str = "nothing was scored", refitted: str = "the instrument frame") -> None:
    """Refuse a file the model misses by centimetres: it belongs to another robot, tool or set-up.

    ``errors`` ``(n, 3)`` m: the model's on the file, ``refitted`` (the instrument frame, or also the
    tool) re-fitted to it first where ``register``. ``refused``: what the caller leaves undone, for the message.

    Raises:
        DataError: naming the median error and the likely cause (``--register`` when the frame was not re-fitted).
    """
    median_mm = float(errors.norm(dim=-1).median()) * 1e3
    if median_mm <= FOREIGN_FILE_MEDIAN_MM:
        return
    cause = (f"even with {refitted} re-fitted to its points: the file is of another robot or set-up "
             "(or its x, y, z columns are swapped)"
             if register else
             "the instrument was moved since the fit (then add --register to re-fit its frame), or the file is of "
             "another robot, tool or set-up")
    raise DataError(f"the model {stored.folder} ({stored.robot.name}) misses these poses by {median_mm:.1f} mm "
                    f"(median; a calibrated arm: well under 1 mm): {cause}; {refused}", path=data.source)
