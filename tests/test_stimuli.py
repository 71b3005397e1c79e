"""Touches: smooth footprints against exact area fractions, gradients, time courses, several
touches, checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.scene import _touches
from diffeit.scene._shapes import Disc, Ellipse, default_edge_width, shape_fraction
from diffeit.scene._time_courses import Path, Press, Ramp
from diffeit.scene._touches import Touch, check_touches, stimulus, touch_field

CENTRE, RADIUS = np.array([0.23, -0.11]), 0.31  # off the mesh's symmetries, well inside the unit disc


@pytest.fixture(scope="module")
def mesh() -> de.Mesh:
    return de.mesh.disc(16, electrode_width=0.2, h=0.1)


def central_difference(f, x: float, step: float = 1e-6) -> float:
    return float((f(x + step) - f(x - step)) / (2 * step))


# --- Footprints -----------------------------------------------------------------------------


def test_disc_converges_to_area_fraction(mesh):
    exact = de.mesh.disc_fraction(mesh, CENTRE, RADIUS)  # same sample points: the limit edge_width -> 0
    areas = mesh.element_areas
    widths = [0.02, 0.01, 3e-3, 1e-3, 1e-4, 1e-5]
    errors = []  # area-weighted L1 error relative to the disc's area
    for width in widths:
        fraction = np.asarray(shape_fraction(mesh, Disc(CENTRE, RADIUS), edge_width=width))
        assert np.all((fraction >= 0) & (fraction <= 1))
        errors.append(areas @ np.abs(fraction - exact) / (np.pi * RADIUS**2))
    assert np.all(np.diff(errors) < 0), errors
    assert errors[0] > 0.03 and errors[-1] < 3e-5, errors
    # Far below the sample spacing the blur is gone: every sample is 0 or 1 again.
    sharp = shape_fraction(mesh, Disc(CENTRE, RADIUS), edge_width=1e-9)
    np.testing.assert_array_equal(sharp, exact)


def test_blur_adds_pi_width_squared_to_the_area(mesh):
    width = default_edge_width(mesh)
    assert width == pytest.approx(2 * np.sqrt(mesh.element_areas.max()) / 8)
    covered = mesh.element_areas @ np.asarray(shape_fraction(mesh, Disc(CENTRE, RADIUS)))
    # Continuum: pi (r^2 + w^2); the sampling itself errs by about 1e-3 of the area at level 8.
    assert covered == pytest.approx(np.pi * (RADIUS**2 + width**2), rel=1.5e-3)
    assert (covered - np.pi * RADIUS**2) / (np.pi * RADIUS**2) == pytest.approx((width / RADIUS) ** 2, rel=0.3)


def test_ellipse_converges_to_area_fraction(mesh):
    centre, axes, angle = np.array([-0.2, 0.15]), np.array([0.35, 0.15]), 0.6
    points = de.mesh.element_sample_points(mesh, 8) - centre
    along = np.cos(angle) * points[..., 0] + np.sin(angle) * points[..., 1]
    across = np.cos(angle) * points[..., 1] - np.sin(angle) * points[..., 0]
    exact = ((along / axes[0]) ** 2 + (across / axes[1]) ** 2 < 1).mean(axis=1)
    errors = [
        np.abs(np.asarray(shape_fraction(mesh, Ellipse(centre, axes, angle), edge_width=width)) - exact).max()
        for width in (0.02, 3e-3, 1e-4, 1e-9)
    ]
    assert np.all(np.diff(errors) < 0) and errors[-1] == 0, errors
    # A circular ellipse is the disc.
    circle = shape_fraction(mesh, Ellipse(CENTRE, (RADIUS, RADIUS), 1.1))
    np.testing.assert_allclose(circle, shape_fraction(mesh, Disc(CENTRE, RADIUS)), rtol=0, atol=1e-13)


def test_gradients_match_finite_differences(mesh):
    x = mesh.element_centroids[:, 0]
    weights = mesh.element_areas * (x + x**2)  # moments of order 1 and 2: they move with every parameter

    @jax.jit
    def moment(centre, radius, axes=(0.3, 0.12), angle=0.4):
        disc = shape_fraction(mesh, Disc(centre, radius))
        ellipse = shape_fraction(mesh, Ellipse(centre[::-1], jnp.asarray(axes), angle))
        return jnp.sum(weights * (disc + 0.5 * ellipse))

    centre = jnp.asarray(CENTRE)
    grads = jax.grad(moment, argnums=(0, 1, 2, 3))(centre, RADIUS, jnp.array([0.3, 0.12]), 0.4)
    expected = [
        central_difference(lambda v: moment(centre.at[0].set(v), RADIUS), CENTRE[0]),
        central_difference(lambda v: moment(centre.at[1].set(v), RADIUS), CENTRE[1]),
        central_difference(lambda v: moment(centre, v), RADIUS),
        central_difference(lambda v: moment(centre, RADIUS, axes=(v, 0.12)), 0.3),
        central_difference(lambda v: moment(centre, RADIUS, axes=(0.3, v)), 0.12),
        central_difference(lambda v: moment(centre, RADIUS, angle=v), 0.4),
    ]
    computed = [*grads[0], grads[1], *grads[2], grads[3]]
    np.testing.assert_allclose(np.array(computed), expected, rtol=1e-5)
    assert min(abs(e) for e in expected) > 1e-4  # none of them trivially zero


@pytest.mark.parametrize(
    ("centre", "radius"),
    [
        ((0.0, 0.0), 0.2),
        pytest.param((0.23, -0.11), 0.31, marks=pytest.mark.slow),
        pytest.param((-0.4, 0.25), 0.15, marks=pytest.mark.slow),
    ],
)
def test_radius_gradient_is_the_circumference(mesh, centre, radius):
    areas = mesh.element_areas

    def area(centre, radius):
        return jnp.sum(areas * shape_fraction(mesh, Disc(centre, radius)))

    d_centre, d_radius = jax.grad(area, argnums=(0, 1))(jnp.asarray(centre), radius)
    assert d_radius == pytest.approx(2 * np.pi * radius, rel=1e-3)
    assert np.abs(d_centre).max() < 1e-3 * 2 * np.pi * radius  # moving a touch inside keeps its area


def test_transformations(mesh):
    radii = jnp.array([0.1, 0.2, 0.3])
    batched = jax.vmap(lambda r: shape_fraction(mesh, Disc(CENTRE, r)))(radii)
    one_by_one = np.stack([shape_fraction(mesh, Disc(CENTRE, r)) for r in radii])
    np.testing.assert_allclose(batched, one_by_one, rtol=1e-14, atol=1e-15)
    touch = Touch(Disc(CENTRE, RADIUS), -0.3, Press(1.0, 0.5, 2.0, 0.5))
    jitted = jax.jit(lambda touch, t: touch_field(mesh, touch, t))(touch, 2.0)
    np.testing.assert_allclose(jitted, touch_field(mesh, touch, 2.0), rtol=1e-14, atol=1e-15)
    # Lists become arrays (one leaf each, not one per number), so a touch built from them jits.
    listed = Touch(Disc(Path([0.0, 1.0], [[0.0, 0.0], [0.3, 0.0]]), 0.2), -0.3)
    assert len(jax.tree_util.tree_leaves(listed)) == 4  # times, waypoints, radius, amplitude
    frames = jax.jit(lambda touch: stimulus(mesh, [touch], jnp.array([0.5])))(listed)
    np.testing.assert_allclose(frames[0], -0.3 * shape_fraction(mesh, Disc((0.15, 0.0), 0.2)), rtol=1e-13, atol=1e-16)
    # Touches built from traced values are not checked, and differentiate.
    d_amplitude = jax.grad(lambda a: jnp.sum(touch_field(mesh, Touch(Disc(CENTRE, RADIUS), a), 0.0)))(-0.3)
    assert d_amplitude == pytest.approx(float(jnp.sum(shape_fraction(mesh, Disc(CENTRE, RADIUS)))), rel=1e-14)


# --- Time courses ---------------------------------------------------------------------------


def test_press_key_times():
    press = Press(start=1.0, ramp_in=0.5, hold=2.0, ramp_out=0.25)
    times = jnp.array([0.0, 1.0, 1.25, 1.5, 2.5, 3.5, 3.625, 3.75, 10.0])
    np.testing.assert_array_equal(press(times), [0, 0, 0.5, 1, 1, 1, 0.5, 0, 0])
    assert press.end == 3.75
    slope = jax.vmap(jax.grad(press))(jnp.array([0.5, 1.25, 2.0, 3.625, 5.0]))
    np.testing.assert_array_equal(slope, [0, 2, 0, -4, 0])
    # Smoothstep ramps: same key values, 3s^2 - 2s^3 between, zero slope at the ends of the ramp.
    smooth = Press(start=1.0, ramp_in=0.5, hold=2.0, ramp_out=0.25, smooth=True)
    np.testing.assert_array_equal(smooth(times), [0, 0, 0.5, 1, 1, 1, 0.5, 0, 0])
    assert smooth(1.125) == 0.15625  # s = 1/4
    slope = jax.vmap(jax.grad(smooth))(jnp.array([1.0, 1.25, 1.5, 3.625]))
    np.testing.assert_allclose(slope, [0, 3, 0, -6], atol=1e-12)
    # Steps are right-continuous: on from the press time, off from the release time.
    step = Press(start=1.0, ramp_in=0.0, hold=2.0, ramp_out=0.0)
    np.testing.assert_array_equal(step(jnp.array([0.999, 1.0, 2.999, 3.0])), [0, 1, 1, 0])


def test_path_interpolation():
    points = np.array([[0.0, 0.0], [0.2, 0.0], [0.2, 0.4]])
    path = Path(times=[0.0, 1.0, 3.0], values=points)
    np.testing.assert_array_equal(path(jnp.array([0.0, 1.0, 3.0])), points)  # exact at the waypoints
    np.testing.assert_allclose(path(-1.0), points[0], atol=0)
    np.testing.assert_allclose(path(0.5), [0.1, 0.0], rtol=1e-15)
    np.testing.assert_allclose(path(2.0), [0.2, 0.2], rtol=1e-15)
    np.testing.assert_allclose(path(7.0), points[-1], atol=0)
    np.testing.assert_allclose(jax.jacfwd(path)(2.0), [0.0, 0.2], rtol=1e-15)  # velocity (m/s)
    smooth = Path(times=[0.0, 1.0, 3.0], values=points, smooth=True)
    np.testing.assert_allclose(smooth(0.25), [0.2 * 0.15625, 0.0], rtol=1e-15)
    np.testing.assert_allclose(jax.jacfwd(smooth)(1.0), [0.0, 0.0], atol=1e-15)  # stops at the waypoint
    # A straight move as a Ramp of points, at several times at once: (T, 2).
    move = Ramp(jnp.array([0.0, 0.0]), jnp.array([0.1, 0.2]), start=1.0, duration=2.0)
    np.testing.assert_allclose(move(jnp.array([0.0, 2.0, 3.0])), [[0, 0], [0.05, 0.1], [0.1, 0.2]], rtol=1e-15)
    # Differentiable in the waypoints and their times.
    d_time = jax.grad(lambda t1: Path(jnp.array([0.0, t1, 3.0]), points)(0.5)[0])(1.0)
    assert d_time == pytest.approx(-0.1, rel=1e-12)  # x = 0.2 * 0.5 / t1


def test_sliding_and_growing_touch(mesh):
    slide = Touch(Disc(Path([0.0, 2.0], [[-0.3, 0.0], [0.3, 0.2]]), 0.15), amplitude=-0.4)
    np.testing.assert_allclose(
        touch_field(mesh, slide, 0.5), -0.4 * shape_fraction(mesh, Disc((-0.15, 0.05), 0.15)), rtol=1e-13, atol=1e-16
    )
    grow = Touch(Disc(CENTRE, Ramp(0.1, 0.3, start=1.0, duration=2.0)), amplitude=-0.4)
    for t, radius in [(0.0, 0.1), (1.0, 0.1), (2.0, 0.2), (3.0, 0.3), (9.0, 0.3)]:
        np.testing.assert_allclose(
            touch_field(mesh, grow, t), -0.4 * shape_fraction(mesh, Disc(CENTRE, radius)), rtol=1e-13, atol=1e-16
        )
    # Ellipse turning in time, semi-axes swapping: a course may stand for any parameter.
    turn = Ellipse(CENTRE, Ramp(jnp.array([0.3, 0.1]), jnp.array([0.1, 0.3])), Ramp(0.0, np.pi / 2))
    np.testing.assert_allclose(
        shape_fraction(mesh, turn, 0.5), shape_fraction(mesh, Ellipse(CENTRE, (0.2, 0.2), np.pi / 4)), atol=1e-13
    )


# --- Several touches ------------------------------------------------------------------------


def test_stimulus_over_frames(mesh):
    times = jnp.array([0.0, 0.5, 1.0, 1.5, 2.0, 4.0])
    first = Touch(Disc((-0.5, 0.0), 0.15), -0.3, Press(0.5, 0.5, 1.0, 0.0))
    second = Touch(Ellipse((0.45, 0.1), (0.2, 0.1), 0.3), -0.5, Press(1.0, 0.0, 0.5, 1.0), edge_width=0.01)
    frames = stimulus(mesh, [first, second], times)
    assert frames.shape == (6, mesh.n_elements)
    alone = [np.stack([touch_field(mesh, touch, t) for t in times]) for touch in (first, second)]
    # The touches lie apart: where one is non-zero the other is below rounding, so they add.
    np.testing.assert_allclose(frames, alone[0] + alone[1], rtol=1e-13, atol=1e-16)
    for frame in (0, 1, 5):  # before the presses, at the foot of the first ramp, after both releases
        np.testing.assert_array_equal(frames[frame], 0)
    left = mesh.element_centroids[:, 0] < 0
    for frame, first_depth, second_depth in [(2, -0.3, -0.5), (3, -0.3, -0.5), (4, 0.0, -0.25)]:
        assert frames[frame][left].min() == pytest.approx(first_depth, abs=1e-6)
        assert frames[frame][~left].min() == pytest.approx(second_depth, abs=1e-6)
    np.testing.assert_allclose(frames[4], alone[1][4], rtol=1e-12)  # the first touch released: only the second
    np.testing.assert_array_equal(stimulus(mesh, [], times), np.zeros((6, mesh.n_elements)))


def test_overlapping_touches_add_resistance(mesh):
    touch = Touch(Disc(CENTRE, RADIUS), -0.7)
    double = np.asarray(stimulus(mesh, [touch, touch], [0.0])[0])
    single = np.asarray(touch_field(mesh, touch, 0.0))
    rho = -single / (1 + single)  # relative resistance change of one touch
    np.testing.assert_allclose(double, -2 * rho / (1 + 2 * rho), rtol=1e-13, atol=1e-16)
    assert double.min() == pytest.approx(-(2 * 0.7 / 0.3) / (1 + 2 * 0.7 / 0.3), abs=1e-9)  # -0.8235, not -1.4
    # In any order, touches alike (computed together) or not, and small changes simply add.
    first, third = (Touch(Disc(CENTRE, RADIUS), amplitude) for amplitude in (-0.3, 0.2))
    second = Touch(Ellipse(CENTRE, (0.3, 0.15), 0.4), -0.6, Press(0.0, 1.0))
    together = np.asarray(stimulus(mesh, [first, second, third], [0.5])[0])
    np.testing.assert_allclose(stimulus(mesh, [third, second, first], [0.5])[0], together, rtol=1e-14, atol=1e-17)
    a, b, c = (np.asarray(touch_field(mesh, touch, 0.5)) for touch in (first, second, third))
    assert np.sum((np.abs(a) > 0.1) & (np.abs(b) > 0.1)) > 10  # the ellipse pressed, over the disc
    ab = (a + b + 2 * a * b) / (1 - a * b)  # pairwise, twice
    np.testing.assert_allclose(together, (ab + c + 2 * ab * c) / (1 - ab * c), rtol=1e-13, atol=1e-16)
    small = [Touch(Disc(CENTRE, RADIUS), amplitude) for amplitude in (1e-6, -2e-6)]
    assert float(stimulus(mesh, small, [0.0])[0].min()) == pytest.approx(-1e-6, rel=1e-5)


def test_zero_amplitude_is_exactly_nothing(mesh):
    silent = Touch(Disc(CENTRE, RADIUS), 0.0)
    np.testing.assert_array_equal(touch_field(mesh, silent, 1.0), 0)
    loud = Touch(Disc((0.1, 0.2), 0.2), -0.4, Press(0.0, 1.0, 1.0, 1.0))
    times = jnp.linspace(0.0, 3.0, 7)
    np.testing.assert_array_equal(stimulus(mesh, [loud, silent], times), stimulus(mesh, [loud], times))
    np.testing.assert_array_equal(stimulus(mesh, [silent, loud], times), stimulus(mesh, [loud], times))


def test_stimulus_gradients_and_batches(mesh, monkeypatch):
    times = jnp.linspace(0.0, 2.0, 5)
    areas = mesh.element_areas

    @jax.jit
    def loss(amplitude, x, start):
        # Unequal ramps: the derivatives in the press time at the two ramps do not cancel.
        touch = Touch(Disc(jnp.stack([x, 0.1]), 0.2), amplitude, Press(start, 0.5, 0.5, 0.25))
        return jnp.sum(areas * mesh.element_centroids[:, 0] * stimulus(mesh, [touch], times))

    grads = jax.grad(loss, argnums=(0, 1, 2))(-0.3, 0.2, 0.3)
    expected = [
        central_difference(lambda v: loss(v, 0.2, 0.3), -0.3),
        central_difference(lambda v: loss(-0.3, v, 0.3), 0.2),
        central_difference(lambda v: loss(-0.3, 0.2, v), 0.3),
    ]
    np.testing.assert_allclose(grads, expected, rtol=1e-5)
    # Frames mapped a few at a time give the same frames.
    touch = Touch(Disc((0.2, 0.1), 0.2), -0.3, Press(0.3, 0.5, 0.5, 0.5))
    whole = stimulus(mesh, [touch], times)
    monkeypatch.setattr(_touches, "_SAMPLES_PER_BATCH", 2 * mesh.n_elements * 64)
    np.testing.assert_allclose(stimulus(mesh, [touch], times), whole, rtol=1e-14, atol=1e-16)


# --- Checks ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: Disc((0.0, 0.0), 0.0), r"Disc\.radius must be positive"),
        (lambda: Disc((0.0, 0.0), Ramp(0.1, -0.1)), r"Disc\.radius must be positive"),
        (lambda: Disc((0.0, 0.0, 0.0, 0.0), 0.1), r"Disc\.centre must be a point"),
        (lambda: Ellipse((0.0, 0.0), (0.2, -0.1)), r"Ellipse\.semi_axes must be positive"),
        (lambda: Ellipse((0.0, 0.0), (0.2, 0.1), np.nan), r"Ellipse\.angle must be finite"),
        (lambda: Touch(Disc((0.0, 0.0), 0.1), -1.0), r"Touch\.amplitude .* must be > -1"),
        (lambda: Touch(Disc((0.0, 0.0), 0.1), -0.3, Ramp(0.0, 2.0)), r"Touch\.envelope must take numbers in \[0, 1\]"),
        (lambda: Touch(Disc((0.0, 0.0), 0.1), -0.3, edge_width=0.0), r"Touch\.edge_width must be a positive"),
        (lambda: Touch((0.0, 0.0), -0.3), r"Touch\.shape must be a Disc or an Ellipse"),
        (lambda: Path([0.0, 1.0, 1.0], [0.0, 1.0, 2.0]), r"Path\.times must be strictly increasing.*times\[2\]"),
        (lambda: Path([0.0], [0.0]), r"Path\.times must be a 1D array of at least 2"),
        (lambda: Path([0.0, 1.0], [0.0, 1.0, 2.0]), r"Path\.values must have one waypoint per time"),
        (lambda: Press(ramp_in=-0.1), r"Press\.ramp_in is a duration: it must be >= 0"),
        (lambda: Press(hold=-1.0), r"Press\.hold is a duration"),
        (lambda: Press(ramp_out=-1.0), r"Press\.ramp_out is a duration"),
        (lambda: Ramp(0.1, 0.2, duration=-1.0), r"Ramp\.duration must be >= 0"),
        (lambda: Ramp(0.1, (0.2, 0.3)), r"Ramp\.initial and Ramp\.final must have one shape"),
    ],
)
def test_bad_values_refused(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_touch_off_the_skin_refused(mesh):
    with pytest.raises(ValueError, match=r"touches\[0\]\.shape\.centre lies outside the skin"):
        touch_field(mesh, Touch(Disc((1.2, 0.0), 0.1), -0.3), 0.0)
    overhanging = Touch(Disc((0.9, 0.0), 0.3), -0.3)  # centre on the skin: allowed
    assert float(jnp.sum(touch_field(mesh, overhanging, 0.0))) < 0
    leaving = Touch(Disc(Path([0.0, 1.0, 2.0], [[0.0, 0.0], [0.5, 0.0], [1.5, 0.0]]), 0.1), -0.3)
    with pytest.raises(ValueError, match=r"touches\[1\]\.shape\.centre \(along its path\) lies outside"):
        stimulus(mesh, [overhanging, leaving], [0.0])
    # On a non-convex skin both ends of a straight slide may be on it and the middle not.
    corners = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], dtype=float)  # metres
    l_shape = de.mesh.polygon(corners, 16, electrode_width=0.2, h=0.2, electrode_centres=0.5 * np.arange(16))
    across = Touch(Ellipse(Ramp(jnp.array([0.5, 1.8]), jnp.array([1.8, 0.5])), (0.2, 0.1)), -0.3)
    check_touches(l_shape, [Touch(Disc((0.5, 1.8), 0.1), -0.3)])
    with pytest.raises(ValueError, match=r"along its path\) lies outside the skin"):
        check_touches(l_shape, [across])


def test_other_bad_inputs_refused(mesh):
    touch = Touch(Disc(CENTRE, RADIUS), -0.3)
    with pytest.raises(ValueError, match=r"level must be a positive integer"):
        touch_field(mesh, touch, 0.0, level=0)
    with pytest.raises(ValueError, match=r"times must be a 1D array"):
        stimulus(mesh, [touch], 0.0)
    with pytest.raises(ValueError, match=r"touches\[0\] must be a Touch"):
        stimulus(mesh, [Disc(CENTRE, RADIUS)], [0.0])
    increase = Touch(Disc(CENTRE, RADIUS), 1.5)  # resistance -60% each: together -120%
    with pytest.raises(ValueError, match=r"increases \(positive Touch.amplitude\) \[1.5, 1.5\], pressed at once"):
        stimulus(mesh, [increase, increase], [0.0])
    # Pressed one after the other they never add up; overlapping in time they do.
    first, second, third = (Touch(Disc(CENTRE, RADIUS), 1.5, Press(start=s, hold=1.0)) for s in (0.0, 1.0, 1.5))
    field = stimulus(mesh, [first, second], [0.5, 1.5])
    np.testing.assert_allclose(field, stimulus(mesh, [first], [0.5, 0.5]), atol=1e-12)
    with pytest.raises(ValueError, match=r"increases \(positive Touch.amplitude\) \[1.5, 1.5\], pressed at once"):
        stimulus(mesh, [first, second, third], [0.0])
