import io
import warnings

import numpy as np
import pytest
import torch

from torchcal.compensate.linalg import CONTRIB_DOMAIN, gauss_jordan, ort_solve, spd_inverse


def random_spd(batch: int, n: int, seed: int, damping: float = 1e-6) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    j = torch.randn(batch, n, n, generator=gen, dtype=torch.float64)
    return j @ j.transpose(-1, -2) + damping * torch.eye(n, dtype=torch.float64)


@pytest.mark.parametrize("n", [3, 6])
def test_gauss_jordan_matches_lapack(n):
    a = random_spd(500, n, seed=n)
    b = torch.randn(500, n, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    x = gauss_jordan(a, b)
    ref = torch.linalg.solve(a, b)
    cond = torch.linalg.cond(a)
    # backward-stable: error bounded by cond * eps
    rel = (x - ref).norm(dim=(-2, -1)) / ref.norm(dim=(-2, -1))
    assert (rel <= 1e3 * cond * torch.finfo(torch.float64).eps).all()
    assert torch.allclose(a @ x, b, atol=1e-8 * b.abs().max())


def test_spd_inverse_is_inverse():
    a = random_spd(100, 6, seed=4, damping=1e-2)
    inv = spd_inverse(a)
    eye = torch.eye(6, dtype=torch.float64).expand_as(a)
    assert torch.allclose(inv @ a, eye, atol=1e-9)


class _Solve(torch.nn.Module):
    def forward(self, m: torch.Tensor) -> torch.Tensor:
        a = m[:, :, :6] @ m[:, :, :6].transpose(-1, -2) + 1e-3 * torch.eye(6, dtype=m.dtype)
        return gauss_jordan(a, m[:, :, 6:])


def test_gauss_jordan_exports_to_onnx_and_runs_in_onnxruntime():
    import onnx
    import onnxruntime as ort

    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(_Solve(), (torch.zeros(2, 6, 7, dtype=torch.float64),), buffer, dynamo=False,
                          opset_version=17, input_names=["m"], output_names=["x"], dynamic_axes={"m": {0: "b"}})
    ops = {node.op_type for node in onnx.load_from_string(buffer.getvalue()).graph.node}
    assert not ops & {"If", "Loop", "Inverse"}
    m = torch.randn(300, 6, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    session = ort.InferenceSession(buffer.getvalue(), providers=["CPUExecutionProvider"])
    got = session.run(None, {"m": m.numpy()})[0]
    a = m[:, :, :6] @ m[:, :, :6].transpose(-1, -2) + 1e-3 * torch.eye(6, dtype=torch.float64)
    np.testing.assert_allclose(got, torch.linalg.solve(a, m[:, :, 6:]).numpy(), rtol=1e-7, atol=1e-9)


class _OrtSolve(torch.nn.Module):
    def forward(self, m: torch.Tensor) -> torch.Tensor:
        a = m[:, :, :6] @ m[:, :, :6].transpose(-1, -2) + 1e-3 * torch.eye(6, dtype=m.dtype)
        return ort_solve(a, m[:, :, 6:])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_ort_solve_is_one_contrib_node_and_matches_lapack_in_onnxruntime(dtype):
    import onnx
    import onnxruntime as ort

    buffer = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(_OrtSolve(), (torch.zeros(2, 6, 7, dtype=dtype),), buffer, dynamo=False, opset_version=17,
                          input_names=["m"], output_names=["x"], dynamic_axes={"m": {0: "b"}},
                          custom_opsets={CONTRIB_DOMAIN: 1})
    graph = onnx.load_from_string(buffer.getvalue()).graph
    inverse = [node for node in graph.node if node.op_type == "Inverse"]
    assert len(inverse) == 1 and inverse[0].domain == CONTRIB_DOMAIN
    assert not {node.op_type for node in graph.node} & {"Div", "If", "Loop"}  # no elimination left
    m = torch.randn(300, 6, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    session = ort.InferenceSession(buffer.getvalue(), providers=["CPUExecutionProvider"])
    got = session.run(None, {"m": m.to(dtype).numpy()})[0]
    mm = m.to(dtype).double()
    a = mm[:, :, :6] @ mm[:, :, :6].transpose(-1, -2) + 1e-3 * torch.eye(6, dtype=torch.float64)
    ref = torch.linalg.solve(a, mm[:, :, 6:]).numpy()
    tol = {"rtol": 1e-8, "atol": 1e-10} if dtype == torch.float64 else {"rtol": 1e-2, "atol": 1e-3}
    np.testing.assert_allclose(got, ref, **tol)
    # eager torch agrees with LAPACK as well (the graphs are also run in torch)
    np.testing.assert_allclose(_OrtSolve()(m).numpy(), torch.linalg.solve(
        m[:, :, :6] @ m[:, :, :6].transpose(-1, -2) + 1e-3 * torch.eye(6, dtype=torch.float64), m[:, :, 6:]).numpy(), rtol=1e-8, atol=1e-10)
