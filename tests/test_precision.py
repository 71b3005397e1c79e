"""float64 by default in a program that did not ask for it: building a model, or computing with
the memory model on images without one, turns JAX's float64 on with a `PrecisionWarning`.

Each check runs in a fresh process (the suite itself turns float64 on in conftest)."""

import json
import subprocess
import sys

import pytest

# A labelled-press memory session on a small mesh: the press memory fit stalled short of its
# tolerance in float32 and raised; its images and times come back float64 after the warning.
PRESS_FIT = """
import json, warnings
import numpy as np
import diffeit as de
from diffeit.memory import MemoryParameters, memory_response
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    truth = MemoryParameters(fast_fraction=0.25, fast_time=0.8, slow_fraction=0.35, slow_time=6.0, relaxation=0.2)
    mesh = de.mesh.disc(16, h=0.3)
    patterns = np.stack([de.mesh.disc_fraction(mesh, c, 0.35) for c in ((-0.4, 0.3), (0.4, -0.2))])
    windows = np.array([[1.0, 3.0], [12.0, 16.0]])
    times = np.arange(300) * 0.1
    held = (times[:, None] >= windows[:, 0]) & (times[:, None] <= windows[:, 1])
    response = memory_response((held * np.array([-0.3, -0.2])) @ patterns, times, truth)
    noise = 0.003 * np.random.default_rng(0).standard_normal(response.shape)
    fit = de.fit.memory_from_presses(np.asarray(response) + noise, times, patterns, windows)
print(json.dumps({
    "response": str(response.dtype),
    "result": str(fit.result == de.results.RESULTS.successful),
    "slow_time": float(fit.memory.slow_time),
    "warnings": [str(w.message) for w in caught if isinstance(w.message, de.PrecisionWarning)],
}))
"""


@pytest.fixture(scope="module")
def fresh_press_fit() -> dict:
    run = subprocess.run([sys.executable, "-c", PRESS_FIT], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1])


def test_memory_on_images_alone_computes_in_float64_and_says_so_once(fresh_press_fit):
    assert fresh_press_fit["response"] == "float64"
    assert len(fresh_press_fit["warnings"]) == 1
    assert "jax_enable_x64" in fresh_press_fit["warnings"][0]


def test_the_press_memory_fit_converges_in_a_program_that_did_not_ask_for_float64(fresh_press_fit):
    assert fresh_press_fit["result"] == "True"
    assert fresh_press_fit["slow_time"] == pytest.approx(6.0, rel=0.1)
