"""Hyperparameter selection against its definitions computed the slow, explicit way, and the
conversion to EIDORS's and pyEIT's values against pyEIT itself."""

import jax.numpy as jnp
import matplotlib.image
import numpy as np
import pytest
from pyeit.eit import protocol as pyeit_protocol
from pyeit.eit.jac import JAC
from pyeit.mesh import PyEITMesh

import diffeit as de
from diffeit.inverse import LinearisedProblem, Noser, OneStep, Tikhonov, select_hyperparameter
from diffeit.plotting import plot_hyperparameter_selection
from diffeit.results import RESULTS, SolverError


@pytest.fixture(scope="module")
def case():
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16))
    reference = np.asarray(model.measure(jnp.ones(mesh.n_elements)))
    touched = np.asarray(model.measure(jnp.asarray(1 + 2 * de.mesh.disc_fraction(mesh, (0.3, -0.4), 0.2))))
    rng = np.random.default_rng(1)
    noise = 0.01 * np.sqrt(np.mean(reference**2)) * rng.standard_normal(reference.shape)
    return model, touched - reference + noise


def _explicit(model, difference, hyperparameter):
    """Residual norm, prior norm and GCV from the explicit reconstruction matrix."""
    problem = LinearisedProblem(model, "noser")
    reconstruction = OneStep(model, "noser", hyperparameter)
    y = difference / problem.data_scale
    x = np.asarray(reconstruction.solve(difference).value)  # dsigma = x at background 1
    residual = problem.jacobian @ x - y
    influence = problem.jacobian @ (np.asarray(reconstruction.matrix) * problem.data_scale)
    m = len(y)
    gcv = m * residual @ residual / (m - np.trace(influence)) ** 2
    # The prior seminorm: x = (P/c) J^T alpha, so x^T (P/c)^-1 x = alpha^T G alpha.
    alpha = np.linalg.lstsq(problem.prior_jacobian, x, rcond=None)[0]
    return np.linalg.norm(residual), np.sqrt(alpha @ problem.gram @ alpha), gcv


def test_curves_match_their_explicit_definitions(case):
    model, difference = case
    candidates = np.array([1e-3, 1e-2, 0.1, 1.0])
    selection = select_hyperparameter(model, difference, "gcv", candidates=candidates)
    for k, hyperparameter in enumerate(candidates):
        residual, solution, gcv = _explicit(model, difference, hyperparameter)
        assert selection.residual_norm[k] == pytest.approx(residual, rel=1e-8)
        assert selection.solution_norm[k] == pytest.approx(solution, rel=1e-6)
        assert selection.criterion[k] == pytest.approx(gcv, rel=1e-8)
    assert selection.value == candidates[np.argmin(selection.criterion)]


def test_discrepancy_lands_on_the_noise_norm(case):
    model, difference = case
    selection = select_hyperparameter(model, difference, "discrepancy", noise=1.0, safety=1.1)
    residual, _, _ = _explicit(model, difference, selection.value)
    expected = 1.1 * 0.01 * np.sqrt(model.n_measurements)  # 1% of RMS(V_ref) per reading, normalised
    assert residual == pytest.approx(expected, rel=1e-6)
    assert selection.target == 1.0 and selection.result == RESULTS.successful


def test_noise_figure_lands_on_its_target(case):
    """NF = SNR_data / SNR_image (EIDORS's choose_noise_figure), recomputed with the explicit
    reconstruction matrix for a small central target."""
    model, difference = case
    selection = select_hyperparameter(model, difference, "noise_figure", noise_figure=0.7)
    mesh = model.mesh
    problem = LinearisedProblem(model, "noser")
    target = de.mesh.disc_fraction(mesh, mesh.element_areas @ mesh.element_centroids / mesh.element_areas.sum(), 0.1)
    data = problem.jacobian @ target
    matrix = np.asarray(OneStep(model, "noser", selection.value).matrix) * problem.data_scale  # y -> x
    weights = mesh.element_areas / mesh.element_areas.sum()
    image_snr = np.sum((weights * (matrix @ data)) ** 2) / np.sum((weights[:, None] * matrix) ** 2)
    data_snr = np.sum(data**2) / len(data)
    assert data_snr / image_snr == pytest.approx(0.7, rel=1e-6)


def test_lcurve_corner_and_gcv_agree_with_the_noise_scale(case):
    """On 1% noise both parameter-free methods pick a hyperparameter within a decade of the
    discrepancy principle's, which knows the noise."""
    model, difference = case
    known = select_hyperparameter(model, difference, "discrepancy", noise=1.0).value
    for method in ("lcurve", "gcv"):
        chosen = select_hyperparameter(model, difference, method).value
        assert known / 10 < chosen < known * 10, (method, chosen, known)


def test_selection_over_frames_and_its_plot(case, tmp_path):
    model, difference = case
    frames = np.stack([difference, 1.5 * difference])
    selection = select_hyperparameter(model, frames, "lcurve")
    assert np.all(np.isfinite(selection.criterion)) and selection.result == RESULTS.successful
    figure = plot_hyperparameter_selection(selection, tmp_path / "curve.png")
    assert len(figure.axes) == 2
    assert matplotlib.image.imread(tmp_path / "curve.png").shape[1] > 1000


def test_selection_refuses_what_it_cannot_do(case):
    model, difference = case
    with pytest.raises(ValueError, match="needs the noise level"):
        select_hyperparameter(model, difference, "discrepancy")
    with pytest.raises(ValueError, match="unknown method 'aic'"):
        select_hyperparameter(model, difference, "aic")
    with pytest.raises(ValueError, match="at least 3 finite positive"):
        select_hyperparameter(model, difference, candidates=[0.1, -1.0, 2.0])
    with pytest.raises(ValueError, match=r"expected \(208,\)"):
        select_hyperparameter(model, difference[:-1])
    options = {"noise": 1.0, "candidates": [1e-6, 1e-5, 1e-4]}
    with pytest.raises(SolverError, match=r"hyperparameter selection by discrepancy: .*widen the candidates"):
        select_hyperparameter(model, difference, "discrepancy", **options)
    tight = select_hyperparameter(model, difference, "discrepancy", **options, throw=False)
    assert tight.result == RESULTS.selection_at_boundary and tight.value == 1e-4


@pytest.mark.parametrize(
    ("prior", "method", "exponent"),
    [
        (Noser(0.5), "kotre", 0.5),
        pytest.param(Noser(0.2), "kotre", 0.2, marks=pytest.mark.slow),
        pytest.param(Tikhonov(), "dgn", 0.5, marks=pytest.mark.slow),
    ],
)
def test_converted_hyperparameter_reproduces_pyeit_exactly(prior, method, exponent):
    """With point electrodes on the same mesh, pyEIT's JAC with the converted `lamb` gives
    diffeit's one-step image to rounding error (and its sign: pyEIT's frames and images match
    diffeit's)."""
    mesh = de.mesh.disc(16, electrode_width=0.2, h=0.1)
    model = de.ForwardModel(mesh, de.protocol.adjacent(16), electrode_model="point")
    background = 2.0
    reference = np.asarray(model.measure(jnp.full(mesh.n_elements, background)))
    touched = np.asarray(
        model.measure(jnp.asarray(background * (1 + 0.5 * de.mesh.disc_fraction(mesh, (0.4, 0.2), 0.2))))
    )
    reconstruction = OneStep(model, prior, 0.1, background=background)
    lamb = de.inverse.to_external_hyperparameter(reconstruction, "pyeit")
    pyeit_mesh = PyEITMesh(
        node=mesh.nodes, element=mesh.triangles, perm=background, el_pos=model.system.electrode_nodes, ref_node=0
    )
    solver = JAC(pyeit_mesh, pyeit_protocol.create(16, dist_exc=1, step_meas=1, parser_meas="std"))
    solver.setup(p=exponent, lamb=lamb, method=method, perm=background)
    theirs = np.real(solver.solve(v1=touched / model.drive_current, v0=reference / model.drive_current))
    ours = np.asarray(reconstruction.solve(touched - reference).value)
    np.testing.assert_allclose(theirs, ours, rtol=1e-8, atol=1e-10 * np.abs(ours).max())
    back = de.inverse.from_external_hyperparameter(lamb, model, "pyeit", prior=prior, background=background)
    assert back == pytest.approx(0.1, rel=1e-12)
    eidors = de.inverse.to_external_hyperparameter(reconstruction, "eidors") if exponent == 0.5 else None
    if eidors is not None:
        assert eidors == pytest.approx(np.sqrt(lamb), rel=1e-12)  # EIDORS squares its hyperparameter


def test_conversion_refuses_priors_without_a_counterpart(case):
    model, _ = case
    with pytest.raises(ValueError, match="no one-step prior of the family Laplace"):
        de.inverse.to_external_hyperparameter(OneStep(model, "laplace", 0.1), "pyeit")
    with pytest.raises(ValueError, match=r"exponent 0\.5"):
        de.inverse.to_external_hyperparameter(OneStep(model, Noser(0.2), 0.1), "eidors")
    with pytest.raises(ValueError, match="unknown tool"):
        de.inverse.to_external_hyperparameter(OneStep(model, "noser", 0.1), "matlab")


def test_a_shared_linearised_problem_gives_the_same_selection(case):
    model, difference = case[0], case[1]
    problem = LinearisedProblem(model, "noser", 1.0)
    for method in ("gcv", "lcurve", "noise_figure"):
        alone = select_hyperparameter(model, difference, method, throw=False)
        shared = select_hyperparameter(model, difference, method, throw=False, problem=problem)
        assert shared.value == alone.value
        np.testing.assert_allclose(shared.criterion, alone.criterion, rtol=1e-12)
    with pytest.raises(ValueError, match="linearised problem of this model"):
        select_hyperparameter(model, difference, normalised=True, reference=np.ones(208), problem=problem)
