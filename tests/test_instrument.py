"""The instrument's effects: noise, common-mode drift, contact impedance drift, open electrodes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffeit as de
from diffeit.scene._instrument import (
    NOISE_LEVELS,
    OPEN_FACTOR,
    CommonModeDrift,
    ContactDrift,
    Noise,
    add_drift,
    add_noise,
    contact_impedance,
    lost_readings,
    open_contact_impedance,
    open_electrodes,
    rms,
)

REFERENCE = jnp.asarray(np.random.default_rng(0).normal(1.0, 0.5, 208))
FRAMES = jnp.asarray(np.random.default_rng(1).normal(1.0, 0.5, (5, 208)))
TIMES = jnp.array([0.0, 0.5, 1.0, 2.5, 10.0])


@pytest.fixture(scope="module")
def model() -> de.ForwardModel:
    return de.ForwardModel(de.mesh.disc(16, h=0.2), de.protocol.adjacent(16), contact_impedance=0.01)


@pytest.mark.parametrize("name", ["low", "medium", "high"])
def test_named_levels_give_documented_std(name):
    noise = Noise.level(name)
    expected = NOISE_LEVELS[name] / 100 * float(rms(REFERENCE))
    zeros = jnp.zeros((50, 208))  # 10,400 samples
    sample = np.asarray(add_noise(zeros, REFERENCE, noise, jax.random.key(7)))
    n = sample.size
    # The sample std of n Gaussian values has a relative standard error of 1/sqrt(2n).
    assert abs(sample.std() / expected - 1) < 3 / np.sqrt(2 * n)
    assert abs(sample.mean()) < 3 * expected / np.sqrt(n)


def test_levels_documented_values():
    assert NOISE_LEVELS == {"low": 0.1, "medium": 0.5, "high": 2.0}


def test_units_agree():
    scale = float(rms(REFERENCE))
    assert float(rms(jnp.array([3.0, -4.0]))) == pytest.approx(np.sqrt(12.5))
    by_percent = Noise.percent(1.0).std(REFERENCE)
    assert float(by_percent) == pytest.approx(0.01 * scale, rel=1e-12)
    assert float(Noise.snr_db(40.0).std(REFERENCE)) == pytest.approx(float(by_percent), rel=1e-12)
    assert float(Noise.volts(0.01 * scale).std(REFERENCE)) == pytest.approx(float(by_percent), rel=1e-12)
    assert float(Noise.level("medium").std(REFERENCE)) == pytest.approx(0.005 * scale, rel=1e-12)
    # SNR of the documented levels: 20 log10(100 / p).
    for name, snr in [("low", 60.0), ("medium", 46.02), ("high", 33.98)]:
        sigma = float(Noise.level(name).std(REFERENCE))
        assert 20 * np.log10(scale / sigma) == pytest.approx(snr, abs=0.01)


def test_seeded_noise():
    noise = Noise.level("high")
    a = add_noise(FRAMES, REFERENCE, noise, jax.random.key(3))
    b = add_noise(FRAMES, REFERENCE, noise, jax.random.key(3))
    c = add_noise(FRAMES, REFERENCE, noise, jax.random.key(4))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.any(np.asarray(a) == np.asarray(c))


def test_zero_effects_are_bit_identical():
    frames = np.asarray(FRAMES)
    for noise in (Noise.percent(0.0), Noise.volts(0.0)):
        out = add_noise(FRAMES, REFERENCE, noise, jax.random.key(0))
        np.testing.assert_array_equal(np.asarray(out), frames)
    np.testing.assert_array_equal(np.asarray(add_drift(FRAMES, TIMES, CommonModeDrift())), frames)


def test_drift_formulas():
    drift = CommonModeDrift(offset=0.1, rate=0.02, amplitude=0.05, period=4.0, phase=0.3, gain_rate=-0.01)
    out = np.asarray(add_drift(FRAMES, TIMES, drift))
    for k, t in enumerate(np.asarray(TIMES)):
        offset = 0.1 + 0.02 * t + 0.05 * np.sin(2 * np.pi * t / 4.0 + 0.3)
        np.testing.assert_allclose(out[k], (1 - 0.01 * t) * np.asarray(FRAMES[k]) + offset, rtol=1e-14, atol=1e-15)
    # t = 1 s, pure offset drift: exactly offset + rate.
    plain = np.asarray(add_drift(jnp.zeros((5, 3)), TIMES, CommonModeDrift(offset=0.5, rate=0.25)))
    np.testing.assert_array_equal(plain[:, 0], [0.5, 0.625, 0.75, 1.125, 3.0])


def test_contact_drift_formulas():
    z0 = jnp.linspace(0.01, 0.02, 16)
    rate = jnp.linspace(-0.1, 0.1, 16)
    z = np.asarray(contact_impedance(z0, TIMES, ContactDrift(rate)))
    assert z.shape == (5, 16)
    np.testing.assert_allclose(z, np.asarray(z0) * np.exp(np.asarray(rate) * np.asarray(TIMES)[:, None]), rtol=1e-14)
    np.testing.assert_array_equal(z[0], np.asarray(z0))
    linear = np.asarray(contact_impedance(jnp.full(16, 0.01), TIMES, ContactDrift(0.05, "linear")))
    np.testing.assert_allclose(linear[:, 3], 0.01 * (1 + 0.05 * np.asarray(TIMES)), rtol=1e-14)


@pytest.mark.slow
def test_contact_drift_feeds_forward_model(model):
    sigma = jnp.ones(model.n_elements)
    z = contact_impedance(jnp.full(16, 0.01), TIMES[:3], ContactDrift(jnp.linspace(0.0, 0.5, 16)))
    frames = jax.vmap(lambda zk: model.measure(sigma, zk))(z)
    assert frames.shape == (3, model.n_measurements)
    np.testing.assert_allclose(np.asarray(frames[0]), np.asarray(model.measure(sigma)), rtol=1e-10)
    assert np.all(np.isfinite(np.asarray(frames)))
    assert not np.allclose(np.asarray(frames[2]), np.asarray(frames[0]), rtol=1e-6)

    # Differentiable in the drift rate through the solve.
    def total(rate):
        zk = contact_impedance(jnp.full(16, 0.01), jnp.array([2.0]), ContactDrift(rate))[0]
        return jnp.sum(model.measure(sigma, zk) ** 2)

    g = float(jax.grad(total)(0.1))
    h = 1e-5
    fd = (float(total(0.1 + h)) - float(total(0.1 - h))) / (2 * h)
    assert g == pytest.approx(fd, rel=1e-5)


def test_open_electrode(model):
    protocol = model.protocol
    sigma = jnp.ones(model.n_elements)
    z = open_contact_impedance(jnp.full(16, 0.01), 5)
    assert float(z[5]) == pytest.approx(0.01 * OPEN_FACTOR)
    assert float(z[4]) == 0.01
    frames = model.measure(sigma, z)[None]
    out, mask = open_electrodes(frames, protocol, 5)
    mask_expected = (
        np.any(protocol.measure[:, [5]] != 0, axis=1)
        | np.any(protocol.drive[:, [5]] != 0, axis=1)[protocol.drive_index]
    )
    np.testing.assert_array_equal(mask, mask_expected)
    # Adjacent, 16 electrodes, 208 readings: 2 drives (26 readings) use electrode 5; 2 of the 13
    # readings of 12 other drives weight it, and 1 of drives (3, 4) and (6, 7) (pairs on a driven
    # electrode are not read).
    assert mask.sum() == 26 + 12 * 2 + 2
    assert np.all(np.asarray(out)[:, mask] == 0.0)
    assert np.all(np.isfinite(np.asarray(out)))
    np.testing.assert_array_equal(np.asarray(out)[:, ~mask], np.asarray(frames)[:, ~mask])
    # Kept readings move a little (up to about 10% next to it): the open electrode stops shunting current.
    kept, intact = np.asarray(out)[0, ~mask], np.asarray(model.measure(sigma))[~mask]
    change = np.abs(kept / intact - 1)
    assert 0.01 < change.max() < 0.15
    np.testing.assert_array_equal(
        lost_readings(protocol, [5, 6]), lost_readings(protocol, 5) | lost_readings(protocol, 6)
    )
    filled, _ = open_electrodes(frames, protocol, [5], fill=5.0)
    assert np.all(np.asarray(filled)[:, mask] == 5.0)


def test_gradients_match_finite_differences():
    def noisy(scale):
        return jnp.sum(add_noise(FRAMES, REFERENCE, Noise.percent(scale), jax.random.key(1)) ** 2)

    def drifted(rate, gain_rate):
        return jnp.sum(add_drift(FRAMES, TIMES, CommonModeDrift(rate=rate, amplitude=0.1, gain_rate=gain_rate)) ** 2)

    def snr(db):
        return jnp.sum(add_noise(FRAMES, REFERENCE, Noise.snr_db(db), jax.random.key(1)) ** 2)

    h = 1e-6
    for f, x in [(noisy, 1.5), (snr, 30.0)]:
        fd = (float(f(x + h)) - float(f(x - h))) / (2 * h)
        assert float(jax.grad(f)(x)) == pytest.approx(fd, rel=1e-6)
    g_rate, g_gain = jax.grad(drifted, argnums=(0, 1))(0.02, 0.01)
    assert float(g_rate) == pytest.approx((float(drifted(0.02 + h, 0.01)) - float(drifted(0.02 - h, 0.01))) / (2 * h))
    assert float(g_gain) == pytest.approx((float(drifted(0.02, 0.01 + h)) - float(drifted(0.02, 0.01 - h))) / (2 * h))
    # Under jit too (the specs are pytrees).
    assert float(jax.jit(jax.grad(noisy))(1.5)) == pytest.approx(float(jax.grad(noisy)(1.5)))


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: Noise.percent(-1.0), "Noise.value"),
        (lambda: Noise.volts(-1e-3), "Noise.value"),
        (lambda: Noise.level("loud"), "Noise.level"),
        (lambda: Noise(1.0, "decibel"), "Noise.kind"),
        (lambda: Noise.percent(float("nan")), "Noise.value"),
        (lambda: CommonModeDrift(period=0.0), "CommonModeDrift.period"),
        (lambda: CommonModeDrift(rate="fast"), "CommonModeDrift.rate"),
        (lambda: ContactDrift(rate=[[0.1]]), "ContactDrift.rate"),
        (lambda: ContactDrift(kind="quadratic"), "ContactDrift.kind"),
        (lambda: open_contact_impedance(jnp.full(16, 0.01), 16), "electrodes"),
        (lambda: lost_readings(de.protocol.adjacent(16), [-1]), "electrodes"),
        (lambda: open_electrodes(FRAMES, de.protocol.adjacent(16), 3, fill=float("nan")), "fill"),
        (lambda: add_drift(FRAMES, TIMES[:2], CommonModeDrift()), "times"),
    ],
)
def test_bad_inputs_name_the_field(make, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.")):
        make()
