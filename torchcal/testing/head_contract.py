"""The contract every residual head meets: it learns a smooth error, exports and stores what it predicts.

Run it for the registered heads (``tests/residual/test_head_contract.py`` does) or for one that lives
outside torchcal::

    from torchcal.testing.head_contract import HeadContract

    class TestMyHead(HeadContract):
        head_name = "my-head"          # its name in torchcal.residual.HEADS

The truth is closed form and computed apart from the head's own code: a smooth function of the
joints (mm) with a material nonlinear part, and the affine least-squares fit of the same features
(numpy) as the bar a head must clearly beat; the prediction the head's stored weights give, written
out in numpy (:func:`closed_form_prediction`), which its ONNX graph run by onnxruntime and the model
folder it is saved to must reproduce. Needs pytest (and onnxruntime for the export test).
"""

from __future__ import annotations

import copy
import io
import math
import warnings

import numpy as np
import pytest
import torch

from torchcal.config.schema import FitConfig
from torchcal.residual import ELM, HEADS, MayflyELM, MLPHead, ResidualHead, rms
from torchcal.residual.features import JointFeatures

#: joint limits of the contract's poses (6 joints, one turn each): features ``[q / pi, sin q, cos q]``
LIMITS = torch.tensor([[-math.pi, math.pi]] * 6, dtype=torch.float64)


def _poses(n: int, seed: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 6, generator=gen, dtype=torch.float64) * 2 - 1) * math.pi


def _target(f: torch.Tensor) -> torch.Tensor:
    # low-order in the features, as a geometric fit leaves it; an affine fit of the features
    # leaves 0.38 of its RMS (the products and the square), which a head has to learn on top
    return torch.stack([0.3 * f[:, 0] + 0.2 * f[:, 1] * f[:, 2], 0.25 * f[:, 1] - 0.1 * f[:, 3] ** 2,
                        0.2 * f[:, 2] * f[:, 4] + 0.1 * f[:, 5]], -1)


def smooth_problem(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Features of ``n`` random 6-joint poses and a smooth 3-D target of them (mm)."""
    f = JointFeatures(LIMITS)(_poses(n, seed))
    return f, _target(f)


def numpy_features(q: np.ndarray) -> np.ndarray:
    """The features of :data:`LIMITS` written out: ``[q / pi, sin q, cos q]``."""
    return np.concatenate([q / math.pi, np.sin(q), np.cos(q)], axis=1)


def linear_baseline_rms(x_train, y_train, x_test, y_test) -> float:
    """Held-out RMS of the affine least-squares map of the features (numpy ``lstsq``)."""
    def affine(x):
        x = np.asarray(x, dtype=np.float64)
        return np.concatenate([x, np.ones((len(x), 1))], axis=1)

    coef = np.linalg.lstsq(affine(x_train), np.asarray(y_train, dtype=np.float64), rcond=None)[0]
    err = np.asarray(y_test, dtype=np.float64) - affine(x_test) @ coef
    return float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))


def _numpy_state(head: ResidualHead) -> dict[str, np.ndarray]:
    return {k: v.detach().cpu().to(torch.float64).numpy() for k, v in head.state().items()}


def _sigmoid(a: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-a))


def elm_layers(head: ResidualHead) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(W, b, V)`` of an ELM-kind head (``sigmoid(x W^T + b) V``) from its stored state; ``None`` otherwise."""
    if not isinstance(head, (ELM, MayflyELM)):
        return None
    state = _numpy_state(head)
    return state["weights"], state["bias"], state["output"]


def closed_form_prediction(head: ResidualHead, x: np.ndarray) -> np.ndarray | None:
    """What a registered head's stored weights give on features ``x``, in numpy; ``None`` for a head of
    another kind (a subclass of :class:`HeadContract` may override :meth:`HeadContract.closed_form`).

    ELM, MMA-ELM: ``sigmoid(x W^T + b) V``. MLP: ``depth`` tanh layers, a linear layer, times the
    stored output scale.
    """
    layers = elm_layers(head)
    if layers is not None:
        w, b, v = layers
        return _sigmoid(x @ w.T + b) @ v
    if isinstance(head, MLPHead):
        settings, state = head.settings(), _numpy_state(head)
        a = x
        for i in range(settings["depth"]):
            a = np.tanh(a @ state[f"{2 * i}.weight"].T + state[f"{2 * i}.bias"])
        last = 2 * settings["depth"]
        return (a @ state[f"{last}.weight"].T + state[f"{last}.bias"]) * settings["output_scale"]
    return None


def _atol(reference: np.ndarray) -> float:
    """Float64 rounding of a few hundred operations on values of this size."""
    return 1e-12 * max(1.0, float(np.abs(reference).max()))


_FITTED: dict[tuple[str, str], ResidualHead] = {}


class HeadContract:
    """Tests every head passes; subclasses set :attr:`head_name` (or parametrize it)."""

    head_name: str
    #: held-out RMS the head must reach, as a share of the affine least-squares fit's held-out RMS
    #: on the same features and poses (that fit already leaves only 0.38 of the target's RMS)
    beat_linear: float = 0.5
    #: held-out RMS after ``refit_output`` on fresh poses, as a share of the fitted head's own
    refit_share: float = 1.25
    #: options the suite builds the head with (small and fast)
    options = FitConfig(residual_hidden=40, mayfly_population=8, mayfly_iterations=8, seed=0, progress=False)

    def closed_form(self, head: ResidualHead, x: np.ndarray) -> np.ndarray | None:
        """The prediction of ``head``'s weights written out apart from its module (``None``: not known)."""
        return closed_form_prediction(head, x)

    @pytest.fixture
    def fitted(self) -> tuple[ResidualHead, torch.Tensor, torch.Tensor]:
        # fitted once per head and options: the tests below only read it (a refit works on a copy)
        key = (self.head_name, repr(self.options))
        if key not in _FITTED:
            x, y = smooth_problem(500, seed=0)
            head = HEADS[self.head_name].from_options(self.options)
            assert isinstance(head, ResidualHead) and head.name == self.head_name
            assert head.fit(x[:400], y[:400], x[400:], y[400:]) is head
            _FITTED[key] = head
        return (_FITTED[key], *smooth_problem(300, seed=1))

    def test_learns_a_smooth_error(self, fitted) -> None:
        head, x_test, y_test = fitted
        x, y = smooth_problem(500, seed=0)  # every pose the head saw (training and validation)
        linear = linear_baseline_rms(x.numpy(), y.numpy(), x_test.numpy(), y_test.numpy())
        # the problem has a nonlinear part worth learning: the affine fit leaves a material share
        assert 0.2 * rms(y_test) < linear < 0.6 * rms(y_test)
        learned = rms(y_test - head.predict(x_test))
        assert learned < self.beat_linear * linear, (
            f"{self.head_name}: held-out RMS {learned:.4f} mm, affine least squares {linear:.4f} mm")

    def test_predicts_the_closed_form_of_its_weights(self, fitted) -> None:
        head, x_test, _ = fitted
        expected = self.closed_form(head, x_test.numpy())
        if expected is None:
            pytest.skip(f"no closed form known for the head '{self.head_name}'")
        np.testing.assert_allclose(head.predict(x_test).numpy(), expected, rtol=0, atol=_atol(expected))

    def test_exported_module_predicts_the_same(self, fitted) -> None:
        """The ONNX graph of ``head.module()``, run by onnxruntime, predicts what the head and its weights do."""
        ort = pytest.importorskip("onnxruntime")
        head, x_test, _ = fitted
        module = copy.deepcopy(head.module()).to(torch.float64).eval()
        buffer = io.BytesIO()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(module, (x_test[:2].clone(),), buffer,  # type: ignore[arg-type]  # a file object
                              dynamo=False, opset_version=17,
                              input_names=["features"], output_names=["error"],
                              dynamic_axes={"features": {0: "batch"}, "error": {0: "batch"}})
        session = ort.InferenceSession(buffer.getvalue(), providers=["CPUExecutionProvider"])
        (onnx_out,) = session.run(None, {"features": x_test.numpy()})
        assert onnx_out.dtype == np.float64 and onnx_out.shape == (len(x_test), 3)
        predicted = head.predict(x_test).numpy()
        np.testing.assert_allclose(onnx_out, predicted, rtol=0, atol=_atol(predicted))
        expected = self.closed_form(head, x_test.numpy())
        if expected is not None:
            np.testing.assert_allclose(onnx_out, expected, rtol=0, atol=_atol(expected))

    def test_rebuilt_from_its_stored_state(self, fitted) -> None:
        head, x_test, _ = fitted
        rebuilt = type(head).from_state(head.settings(), head.state())
        assert torch.allclose(rebuilt.predict(x_test), head.predict(x_test), rtol=0, atol=1e-10)

    def test_model_folder_predicts_what_was_saved(self, fitted, tmp_path) -> None:
        """Saved to a model folder and loaded back (safetensors + JSON), joints in, metres out."""
        from torchcal.stages.residual_store import StoredResidual, load_residual, save_residual

        head, _, _ = fitted
        q = _poses(200, seed=3)
        save_residual(tmp_path, StoredResidual(head, JointFeatures(LIMITS), {}))
        loaded = load_residual(tmp_path)
        assert loaded.head.name == self.head_name and loaded.head.settings() == head.settings()
        out = loaded.to_torch_module().to(torch.float64)
        with torch.no_grad():
            got = out(q).numpy()
        np.testing.assert_allclose(got, loaded.predict_base_error(q).numpy(), rtol=0, atol=1e-15)
        expected = self.closed_form(head, numpy_features(q.numpy()))
        if expected is None:  # no closed form: what the head itself predicts on the same features
            expected = head.predict(JointFeatures(LIMITS)(q)).numpy()
        np.testing.assert_allclose(got, expected * 1e-3, rtol=0, atol=1e-3 * _atol(expected))

    def test_refit_output_keeps_the_head_or_says_none(self, fitted) -> None:
        """``refit_output`` on fresh poses with another target (the sign flipped: any linear output layer
        reaches it) learns that target on other held-out poses, leaves the fitted head alone, and for an
        ELM-kind head keeps the hidden layer and solves the output weights in closed form."""
        head, x_test, y_test = fitted
        before = head.predict(x_test).clone()
        layers_before = elm_layers(head)
        x_new, y_new = smooth_problem(400, seed=2)
        refitted = copy.deepcopy(head).refit_output(x_new, -y_new)
        assert torch.equal(head.predict(x_test), before)  # the copy was refitted, not the head
        if refitted is None:
            return
        own = rms(y_test - before)
        got = rms(-y_test - refitted.predict(x_test))
        assert got < self.refit_share * own, f"refitted held-out RMS {got:.4f} mm vs {own:.4f} mm before"
        if layers_before is None:
            return
        w, b, _ = layers_before
        layers_after = elm_layers(refitted)
        assert layers_after is not None
        w_new, b_new, v_new = layers_after
        assert np.array_equal(w_new, w) and np.array_equal(b_new, b)  # the searched hidden layer is kept
        hidden = _sigmoid(x_new.numpy() @ w.T + b)
        targets = -y_new.numpy()
        lstsq = np.linalg.lstsq(hidden, targets, rcond=None)[0]
        ridge = refitted.settings()["ridge"]
        if ridge is None:
            expected = lstsq
        else:  # the documented estimator: (H^T H + ridge mean(diag H^T H) I)^-1 H^T T
            gram = hidden.T @ hidden
            expected = np.linalg.solve(gram + ridge * np.mean(np.diag(gram)) * np.eye(len(gram)), hidden.T @ targets)
        np.testing.assert_allclose(v_new, expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())
        # and it fits the refit poses as well as plain least squares does
        fit = np.sqrt(np.mean(np.sum((targets - hidden @ v_new) ** 2, axis=1)))
        best = np.sqrt(np.mean(np.sum((targets - hidden @ lstsq) ** 2, axis=1)))
        assert best <= fit <= best * (1 + 1e-6)
