"""Scenes: TOML files with units round-trip, examples load, bad scenes name the field."""

import jax
import numpy as np
import pytest

import diffeit as de
from diffeit.scene import (
    Background,
    CommonModeDrift,
    ContactDrift,
    Disc,
    ElectrodePositionError,
    FoamStack,
    MeasurementNoise,
    Noise,
    OpenElectrodes,
    Path,
    Polygon,
    Press,
    Ramp,
    Region,
    Scene,
    Skin,
    Touch,
    pressure_to_change,
)
from diffeit.scene._units import quantity

SKIN = Skin(h=0.2)


def every_effect_scene() -> Scene:
    return Scene(
        skin=Skin(h=0.2, simulation_h=0.12, contact_impedance=np.linspace(0.01, 0.02, 16), protocol="skip 3"),
        background=Background(0.01, (Region(Polygon([[0, -2], [2, -2], [2, 2], [0, 2]]), 0.002, 0.03),)),
        touches=(
            Touch(Disc([0.5, 0.0], 0.2), -0.3, Press(start=0.2, ramp_in=0.1, hold=0.5, smooth=True)),
            Touch(
                Disc(Path([0.1, 0.6], [[-0.5, 0.0], [0.0, 0.5]]), Ramp(0.1, 0.2, 0.0, 0.5)),
                -0.2,
                edge_width=0.02,
            ),
        ),
        frame_rate=10.0,
        duration=1.0,
        effects=(
            de.scene.bare_skin(),
            MeasurementNoise(Noise.snr_db(40.0), seed=7),
            CommonModeDrift(offset=1e-4, period=2.0),
            ContactDrift(rate=np.linspace(0.0, 0.02, 16), kind="linear"),
            OpenElectrodes((3,), fill=0.0),
            ElectrodePositionError.random(16, 0.01, seed=3),
            de.scene.ReadoutMixing.random(16, 0.3, seed=1),
            de.scene.ReadingGains.random(208, 0.2, seed=2),
        ),
        name="every effect",
        description="one of each",
    )


def assert_same_scene(again: Scene, scene: Scene) -> None:
    """The same pytree (structure with its static data, so a list read back as 16 leaves instead
    of one array fails) and the same leaves, value for value."""
    assert jax.tree_util.tree_structure(again) == jax.tree_util.tree_structure(scene)
    for leaf, expected in zip(jax.tree_util.tree_leaves(again), jax.tree_util.tree_leaves(scene), strict=True):
        np.testing.assert_array_equal(np.asarray(leaf), np.asarray(expected))
    assert again.to_dict() == scene.to_dict()


def test_toml_round_trip_keeps_every_field(tmp_path):
    scene = every_effect_scene()
    path = scene.to_toml(tmp_path / "scene.toml")
    again = Scene.from_toml(path)
    assert_same_scene(again, scene)
    # And once more through text: the written file is a fixed point.
    assert Scene.from_toml_string(again.to_toml_string()).to_toml_string() == path.read_text()
    assert [de.scene._effects.effect_name(e) for e in again.effects] == list(de.scene.EFFECT_NAMES)
    np.testing.assert_array_equal(np.asarray(again.skin.contact_impedance), np.linspace(0.01, 0.02, 16))
    with pytest.raises(FileExistsError):
        scene.to_toml(path)


@pytest.mark.parametrize("name", de.scene.EXAMPLES)
def test_examples_load_and_round_trip(name):
    scene = de.scene.example(name)
    assert scene.name and scene.description
    assert_same_scene(Scene.from_dict(scene.to_dict()), scene)
    assert scene.touches
    assert scene.n_frames == len(scene.times) >= 10


def test_units_convert_to_si():
    text = """
    frame_rate = "0.5 kHz"
    duration = "200 ms"
    [skin]
    radius = "50 mm"
    electrode_width = "5 mm"
    h = "1 cm"
    contact_impedance = "10 ohm mm"
    drive_current = "2 mA"
    [background]
    conductivity = "100 ohm/sq"
    [[touches]]
    centre = ["10 mm", "0 mm"]
    radius = "8 mm"
    amplitude = "-25 %"
    [effects.noise]
    volts = "20 uV"
    """
    scene = Scene.from_toml_string(text)
    assert scene.frame_rate == 500.0 and scene.duration == pytest.approx(0.2)
    assert scene.n_frames == 100
    geometry = dict(scene.skin.geometry)
    assert geometry["radius"] == pytest.approx(0.05) and geometry["electrode_width"] == pytest.approx(0.005)
    assert scene.skin.h == pytest.approx(0.01) and scene.skin.simulation_h == pytest.approx(0.005)
    assert float(scene.skin.contact_impedance) == pytest.approx(0.01)
    assert scene.skin.drive_current == pytest.approx(2e-3)
    assert float(scene.background.conductivity) == pytest.approx(0.01)
    touch = scene.touches[0]
    np.testing.assert_allclose(np.asarray(touch.shape.centre), [0.01, 0.0])
    assert float(touch.amplitude) == pytest.approx(-0.25)
    noise = scene.effect("noise").noise
    assert noise.kind == "volts" and float(noise.value) == pytest.approx(2e-5)
    assert quantity("30 deg", "angle", "a") == pytest.approx(np.pi / 6)
    assert quantity("0.2", "length", "a") == 0.2  # a bare number in a string: SI
    # Noise given in percent stays in percent; a drift rate is in volts per second.
    scene = Scene.from_toml_string('[effects.noise]\npercent = "0.5 %"\n[effects.common_mode_drift]\nrate = "1 mV/s"\n')
    assert float(scene.effect("noise").noise.value) == 0.5 and scene.effect("noise").noise.kind == "percent"
    assert float(scene.effect("common_mode_drift").rate) == pytest.approx(1e-3)


@pytest.mark.slow
def test_per_element_memory_parameters_round_trip_and_simulate():
    """A memory parameter per element of the simulation mesh reads back as one array leaf."""
    scene = Scene(skin=SKIN, touches=(Touch(Disc([0.3, 0.0], 0.3), -0.3, Press(0.1, hold=0.2)),), duration=0.5)
    n_elements = scene.simulation_mesh().n_elements
    gain = np.linspace(0.8, 1.2, n_elements)
    scene = scene.replace(effects=(de.scene.MemoryParameters(gain=gain),))
    again = Scene.from_toml_string(scene.to_toml_string())
    assert_same_scene(again, scene)
    np.testing.assert_array_equal(de.simulate(again, progress=False).frames, de.simulate(scene, progress=False).frames)


def test_pressure_maps_bilinearly():
    # The multi-layer skin paper: 1.3 %/kPa up to 38 kPa, then 0.2 %/kPa, on the relative resistance.
    x = np.array([0.0, 20.0, 38.0, 100.0])
    resistance = np.array([0.0, 0.26, 0.494, 0.494 + 0.002 * 62])
    np.testing.assert_allclose(np.asarray(pressure_to_change(x)), -resistance / (1 + resistance), rtol=1e-14)
    steeper = FoamStack(sensitivity=0.02)
    assert float(pressure_to_change(10.0, steeper)) == pytest.approx(-0.2 / 1.2)
    scene = Scene.from_toml_string('[[touches]]\ncentre = [0, 0]\nradius = 0.2\npressure = "20 kPa"\n')
    assert float(scene.touches[0].amplitude) == pytest.approx(-0.26 / 1.26)
    with pytest.raises(ValueError, match="pressure"):
        pressure_to_change(-1.0)


def test_electrode_position_error_moves_only_the_simulation_mesh():
    offsets = tuple(0.02 * np.sin(np.arange(16)))
    scene = Scene(skin=SKIN, effects=(ElectrodePositionError(offsets),))
    nominal, moved = scene.reconstruction_mesh(), scene.simulation_mesh()

    def centre_angles(mesh):
        return np.array([np.arctan2(*mesh.nodes[chain].mean(axis=0)[::-1]) for chain in mesh.electrodes])

    shift = np.angle(np.exp(1j * (centre_angles(moved) - centre_angles(nominal))))
    np.testing.assert_allclose(shift, offsets, atol=2e-3)  # node chains sample the arc
    assert not np.allclose(shift, 0)


def test_background_regions_and_functions():
    mesh = SKIN.mesh(0.1)
    half = Polygon([[0, -2], [2, -2], [2, 2], [0, 2]])
    values = np.asarray(Background(0.01, (Region(half, 0.002),)).values_on(mesh))
    x = mesh.element_centroids[:, 0]
    far = np.abs(x) > 0.3  # ten edge widths from the boundary at x = 0
    np.testing.assert_allclose(values[far & (x > 0)], 0.002, rtol=1e-12)
    np.testing.assert_allclose(values[far & (x < 0)], 0.01, rtol=1e-12)
    assert np.all((values >= 0.002 - 1e-15) & (values <= 0.01 + 1e-15))
    ramp = np.asarray(Background(function=lambda p: 0.01 + 0.005 * p[..., 0]).values_on(mesh))
    # The mean of a linear function over an element is its value at the centroid.
    np.testing.assert_allclose(ramp, 0.01 + 0.005 * x, rtol=1e-12)
    with pytest.raises(ValueError, match=r"background\.function"):
        Scene(skin=SKIN, background=Background(function=lambda p: 0.01 + 0 * p[..., 0])).to_dict()


BAD_SCENES = [
    ("[background]\nconductivity = -0.01\n", "background.conductivity"),
    ('[background]\nconductivity = "5 mm"\n', "background.conductivity"),
    ("[[touches]]\ncentre = [1.5, 0]\nradius = 0.2\namplitude = -0.3\n", "touches[0].shape.centre"),
    ('[[touches]]\ncentre = [0, 0]\nradius = "0.2 s"\namplitude = -0.3\n', "touches[0].radius"),
    ("[[touches]]\ncentre = [0, 0]\nradius = -0.2\namplitude = -0.3\n", "touches[0]"),
    ("[[touches]]\ncentre = [0, 0]\nradius = 0.2\namplitude = -1.5\n", "touches[0]"),
    ("[[touches]]\ncentre = [0, 0]\nradius = 0.2\n", "touches[0]: give either amplitude"),
    ("[[touches]]\ncentre = [0, 0]\nradus = 0.2\namplitude = -0.3\n", "touches[0]"),
    ("[effects.noize]\nlevel = 'low'\n", "effects.noize"),
    ("[effects.noise]\nlevel = 'deafening'\n", "effects.noise"),
    ("[effects.noise]\npercent = '3 mV'\n", "effects.noise.percent"),
    ("[effects.memory]\nfast_time = -1.0\n", "effects.memory"),
    ("[effects.open_electrode]\nelectrodes = [16]\n", "effects.open_electrode.electrodes"),
    ("[effects.electrode_position_error]\noffsets = [0.0, 0.1]\n", "effects.electrode_position_error.offsets"),
    ('[skin]\nkind = "hexagon"\n', "skin.kind"),
    ('[skin]\nprotocol = "sideways"\n', "skin.protocol"),
    ("[skin]\ncontact_impedance = [0.01, 0.02]\n", "skin.contact_impedance"),
    ('[skin]\nh = "1 kHz"\n', "skin.h"),
    ("frame_rate = 0\n", "frame_rate"),
    ('duration = "3 m"\n', "duration"),
    ("colour = 'red'\n", "unknown keys ['colour']"),
    ('[[touches]]\ncentre = [0, 0]\nradius = 0.2\namplitude = -0.3\nenvelope = { kind = "wobble" }\n', "envelope.kind"),
    (
        '[[touches]]\ncentre = [0, 0]\nradius = 0.2\npressure = { kind = "ramp", start = 0, duration = 1 }\n',
        "touches[0].pressure must be a number",
    ),
    # Inside the reconstruction mesh's rim, outside the finer simulation mesh's.
    ("[[touches]]\ncentre = [0.98763, 0.15615]\nradius = 0.1\namplitude = -0.3\n", "touches[0].shape.centre"),
    (
        '[[background.regions]]\nshape = "disc"\ncentre = [0, 0]\nradius = 0.3\nconductivity = 0.002\n'
        "edge_width = -0.02\n",
        "Region.edge_width",
    ),
    ("[effects.memory]\npreset = []\n", "effects.memory.preset must be a string"),
    ("[effects.noise]\nlevel = []\n", "effects.noise.level must be a string"),
    ('[effects.common_mode_drift]\nrate = "1 mV"\n', "effects.common_mode_drift.rate"),
    ("[effects.contact_drift]\nrate = [0.1, 0.2]\n", "effects.contact_drift.rate has 2 values"),
    ('duration = 0.3\n[effects.contact_drift]\nkind = "linear"\nrate = -5.0\n', "effects.contact_drift: a linear rate"),
    ("[effects.electrode_position_error]\noffsets = [0.35" + ", 0" * 15 + "]\n", "effects.electrode_position_error: "),
    ("[skin]\nradius = -1.0\n", "skin: "),
    ('[skin]\nprotocol = "skip 16"\n', "skin.protocol 'skip 16'"),
]


@pytest.mark.parametrize(("text", "field"), BAD_SCENES)
def test_bad_scenes_name_the_field(text, field):
    with pytest.raises(ValueError, match=field.replace(".", r"\.").replace("[", r"\[").replace("]", r"\]")):
        Scene.from_toml_string(text)


def test_bad_scene_objects_name_the_field():
    with pytest.raises(ValueError, match="'noise' is given twice"):
        Scene(effects=(MeasurementNoise(Noise.percent(1.0)), MeasurementNoise(Noise.percent(2.0))))
    with pytest.raises(ValueError, match=r"effects\[0\] is not an effect"):
        Scene(effects=("noise",))
    with pytest.raises(ValueError, match="not valid TOML"):
        Scene.from_toml_string("frame_rate = = 3")
    with pytest.raises(ValueError, match="unknown example"):
        de.scene.example("two_touches")


SINGLE_TOUCH = de.scene.example_path("single_touch").read_text()


@pytest.mark.parametrize(
    ("content", "message"),
    [
        # Cut within "duration = 2.5": it would read as 2 s.
        (SINGLE_TOUCH[: SINGLE_TOUCH.index("duration = 2.5") + 12].encode(), "the last line does not end in a newline"),
        (b"\x89PNG\r\n\x1a\n\x00\x00", r"is not a scene file: byte 0 is not UTF-8 text"),
        (b"\x89HDF\r\n\x1a\n\x00\x00", r"is not a scene file: byte 0 is not UTF-8 text"),
        (b"", "holds no scene: no key"),
        (b"# a scene, some day\n", "holds no scene: no key"),
        (b"frame_rate = = 3\n", "is not valid TOML"),
        (b"[skin]\nradius = -1.0\n", "skin: "),
        # Refused by the Scene itself: the touch is off the simulation mesh.
        (b"[[touches]]\ncentre = [0.98763, 0.15615]\nradius = 0.1\namplitude = -0.3\n", r"touches\[0\]\.shape\.centre"),
    ],
)
def test_bad_scene_files_are_refused_naming_the_file(tmp_path, content, message):
    path = tmp_path / "scene.toml"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=message) as raised:
        Scene.from_toml(path)
    assert str(raised.value).startswith(str(path))


def test_a_missing_scene_file():
    with pytest.raises(FileNotFoundError, match="no scene file"):
        Scene.from_toml("no/such/scene.toml")


def test_integer_parameters_become_float_leaves():
    """jax.grad refuses integer leaves: `hold=2` or integer vertices must not stop a gradient."""
    scene = Scene(
        skin=Skin(h=0.2, contact_impedance=1),
        background=Background(1, (Region(Polygon([[0, -2], [2, -2], [2, 2], [0, 2]]), 2),)),
        touches=(Touch(Disc([0, 0], 1 / 4), -0.25, Press(0, hold=2)),),
    )
    leaves = jax.tree_util.tree_leaves(scene)
    assert leaves and all(np.issubdtype(np.asarray(leaf).dtype, np.floating) for leaf in leaves)
    assert Touch(Polygon([[0, 0], [1, 0], [0, 1]]), -0.1).shape.vertices.dtype == np.float64
