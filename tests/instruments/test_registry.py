"""The instrument registry: a file's instrument from its header, every built-in instrument, clear errors."""

import pytest

from torchcal.core.errors import DataError
from torchcal.instruments.registry import BUILTIN, get, names, recognise


@pytest.mark.parametrize(
    "header, kind",
    [
        ("q1,q2,q3,q4,q5,q6,x,y,z", "tracker"),
        ("q1,q2,q3,q4,q5,q6,l1,l2,l3,l4", "tracer"),
        ("q1,q2,q3,q4,q5,q6,fx,fy,fz,tx,ty,tz,dx,dy,dz,x,y,z", "stiffness"),
        ("scan,q1,q2,q3,q4,q5,q6,u,w,plane", "profile"),
    ],
)
def test_kind_from_header(tmp_path, header, kind):
    path = tmp_path / "m.csv"
    path.write_text(header + "\n" + ",".join("0" for _ in header.split(",")) + "\n")
    assert recognise(path).name == kind


def test_unknown_header_names_file_and_row(tmp_path):
    path = tmp_path / "odd.csv"
    path.write_text("q1,q2,a,b\n1,2,3,4\n")
    with pytest.raises(DataError, match=r"odd.csv, row 1: cannot tell the measurement kind"):
        recognise(path)


def test_every_registered_instrument_is_one_under_its_name():
    from torchcal.instruments.base import STAGES, Instrument

    assert list(BUILTIN) == names()[: len(BUILTIN)]
    for name in names():
        instrument = get(name)
        assert isinstance(instrument, Instrument) and instrument.name == name
        assert instrument.stage in STAGES and instrument.required_columns


def test_unknown_instrument_is_refused_with_the_choices():
    from torchcal.core.errors import TorchcalError

    with pytest.raises(TorchcalError, match=r"unknown instrument 'laser'; choose one of tracker, tracer"):
        get("laser")


def test_a_header_of_two_equally_specific_instruments_is_ambiguous(tmp_path):
    path = tmp_path / "both.csv"
    path.write_text("scan,q1,q2,u,w,x,y,z\n" + ",".join("0" for _ in range(8)) + "\n")
    with pytest.raises(DataError, match=r"both.csv, row 1: the header fits several instruments \(tracker, profile\)"):
        recognise(path)



def test_only_the_default_instrument_has_the_twin_run():
    """``torchcal run`` reaches the tracker's run through the registry; another instrument refuses it in one line."""
    from torchcal.config.schema import RunConfig
    from torchcal.core.errors import TorchcalError
    from torchcal.instruments.registry import default

    assert default().name == "tracker" and type(default()).run is not type(get("sockets")).run
    with pytest.raises(TorchcalError, match="instrument sockets has no end-to-end twin run"):
        get("sockets").run(RunConfig())
