"""Real data: the Montreal 1995 rod moved in a circle around a tank is imaged going round."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "montreal_rod.py"


def _load_example():
    spec = importlib.util.spec_from_file_location("montreal_rod", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def example():
    return _load_example()


@pytest.fixture(scope="module")
def result(example):
    return example.reconstruct_montreal()


def _fit_circle(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic least-squares circle (Kasa): x^2 + y^2 = 2 a x + 2 b y + c; radius^2 = c + a^2 + b^2."""
    design = np.column_stack([2 * points, np.ones(len(points))])
    (a, b, c), *_ = np.linalg.lstsq(design, np.sum(points**2, axis=1), rcond=None)
    return np.array([a, b]), float(np.sqrt(c + a**2 + b**2))


def test_rod_positions_lie_on_a_circle_and_go_round_one_way(example, result):
    assert result.images.shape == (99, result.mesh.n_elements)
    assert np.all(result.images.min(axis=1) < -np.abs(result.images.max(axis=1)))  # a non-conductive rod
    centre, radius = _fit_circle(result.positions)
    distance = np.abs(np.linalg.norm(result.positions - centre, axis=1) - radius)
    ratio = np.median(distance) / radius
    assert ratio < 0.10, f"median distance to the fitted circle is {ratio:.3f} of its radius {radius:.4f} m"
    assert radius > 0.3 * example.TANK_RADIUS, f"fitted radius {radius:.4f} m: the rod should circle the tank"

    angles = np.unwrap(np.arctan2(*(result.positions - centre).T[::-1]))
    steps = np.diff(angles)
    moving = steps[np.abs(steps) > 1e-3]  # radians: frames where the centroid moved round
    same_way = max(np.mean(moving > 0), np.mean(moving < 0))
    turn = abs(angles[-1] - angles[0])
    assert len(moving) > 0.5 * len(steps), f"only {len(moving)} of {len(steps)} frames move"
    assert same_way >= 0.85, f"{same_way:.3f} of {len(moving)} moving frames turn the same way"
    assert turn > np.pi, f"total turn {turn:.3f} rad"
    print(f"Montreal: median distance / radius {ratio:.4f}, same direction {same_way:.3f}, turn {turn:.3f} rad")


@pytest.mark.slow
def test_example_writes_an_image_strip(example, tmp_path, capsys):
    output = tmp_path / "rod.png"
    example.main(["-o", str(output)])
    assert output.stat().st_size > 20_000
    assert "99 frames" in capsys.readouterr().out
