"""The demo: a touch on the skin is found where it is."""

import matplotlib.image

from diffeit.cli import main
from diffeit.demo import TOUCH_RADIUS, run_demo


def test_demo_images_the_touch_and_writes_a_png(tmp_path):
    result = run_demo(tmp_path / "demo.png", seed=0)
    image = matplotlib.image.imread(result.figure)
    assert image.shape[0] > 300 and image.shape[1] > 600
    assert result.n_data_elements > 2 * result.n_reconstruction_elements  # data from a finer mesh
    # The 1% noise is twice the touch's own signal (0.5% of RMS(V_ref)); a one-step image still
    # puts the touch's half-amplitude centroid within its radius and correlates with the truth.
    assert result.position_error < TOUCH_RADIUS
    assert result.correlation > 0.3
    assert result.peak < 0  # a touch lowers the conductivity


def test_diffeit_demo_command(tmp_path, capsys):
    assert main(["demo", "--output", str(tmp_path / "out.png"), "--seed", "1"]) == 0
    printed = capsys.readouterr().out
    assert "position error" in printed
    assert (tmp_path / "out.png").stat().st_size > 10_000
