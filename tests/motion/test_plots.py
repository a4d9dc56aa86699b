import numpy as np

from torchcal.motion import plots


def test_plots_write_png(tmp_path):
    t = np.linspace(0, 1, 50)
    sigma = np.abs(t - 0.5)
    inside = sigma < 0.1
    qdot = np.stack([np.sin(t * j) for j in range(1, 7)], -1)
    for out in (
        plots.plot_path_error(t, {"a": sigma, "b": 2 * sigma}, tmp_path / "e.png", inside, 0.005),
        plots.plot_joint_speeds(t, {"a": qdot, "b": 100 * qdot}, np.ones(6), tmp_path / "v.png", inside),
        plots.plot_singularity(t, sigma, sigma**2, 0.1, tmp_path / "s.png"),
    ):
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
