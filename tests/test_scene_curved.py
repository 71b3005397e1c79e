"""Scenes on curved skins: touches on a sphere cap and a cylinder patch, simulated and saved."""

import numpy as np
import pytest

import diffeit as de
from diffeit.cli import main
from diffeit.scene import Disc, Ellipse, MeasurementNoise, Noise, Press, Scene, Skin, Touch, touch_field

CAP = Skin(geometry={"kind": "sphere_cap", "radius": 1.0, "polar_angle": 1.2, "n_electrodes": 16}, h=0.1)
RHO = 0.04  # m, a forearm
FOREARM = Skin(
    geometry={"kind": "cylinder_patch", "radius": RHO, "length": 0.15, "angle": np.radians(150), "n_electrodes": 16},
    h=0.012,
)
CENTRE = (RHO * np.cos(0.3), RHO * np.sin(0.3), 0.02)


def test_disc_on_a_sphere_cap_covers_the_spherical_cap_area():
    mesh, s = CAP.mesh(), 0.4  # geodesic radius 0.4 rho: the chord is 0.7% shorter
    centre = (np.sin(0.3), 0.0, np.cos(0.3))
    fraction = np.asarray(touch_field(mesh, Touch(Disc(centre, s), -0.5), 0.0, surface=CAP.surface)) / -0.5
    area = float(np.sum(fraction * mesh.element_areas))
    assert area == pytest.approx(2 * np.pi * (1 - np.cos(s)), rel=0.03)


def test_off_surface_centres_and_flat_shapes_are_refused_by_name():
    mesh = CAP.mesh()
    with pytest.raises(ValueError, match=r"touches\[0\]\.shape\.centre .*from the skin's surface"):
        touch_field(mesh, Touch(Disc((0.0, 0.0, 1.3), 0.2), -0.5), 0.0)
    with pytest.raises(ValueError, match=r"touches\[0\]\.shape: an Ellipse is flat-only"):
        touch_field(mesh, Touch(Ellipse((0.0, 0.0), (0.1, 0.2)), -0.5), 0.0)
    with pytest.raises(ValueError, match=r"centre must be a point \(x, y, z\)"):
        Scene(skin=CAP, touches=(Touch(Disc((0.0, 0.0), 0.2), -0.5),))
    with pytest.raises(ValueError, match="needs"):
        Skin(geometry={"kind": "cylinder_patch", "radius": 0.04, "angle": 2.0}, h=0.01)


def forearm_scene() -> Scene:
    touch = Touch(Disc(CENTRE, 0.012), -0.5, Press(start=0.3, hold=0.4))
    noise = MeasurementNoise(Noise(0.5, "percent"), 0)
    return Scene(skin=FOREARM, touches=(touch,), frame_rate=10.0, duration=1.0, effects=(noise,))


def test_simulate_on_a_cylinder_patch_sees_the_touch_where_it_is():
    simulation = de.simulate(forearm_scene(), progress=False)
    frames, reference = np.asarray(simulation.frames), np.asarray(simulation.reference)
    change = np.linalg.norm(frames - reference, axis=1)
    untouched, touched = change[[0, 1, 2, 8, 9]], change[3:7]  # pressed from 0.3 s to 0.7 s
    assert touched.min() > 2 * untouched.max()  # the untouched frames differ by noise alone
    truth = np.asarray(simulation.truth)
    assert np.ptp(truth[0]) == 0  # the untouched skin
    peak = simulation.mesh.element_centroids[np.argmin(truth[5])]
    assert np.linalg.norm(peak - np.asarray(CENTRE)) < 0.012


def test_a_curved_scene_round_trips_through_toml(tmp_path):
    scene = forearm_scene()
    again = Scene.from_toml(scene.to_toml(tmp_path / "forearm.toml"))
    assert dict(again.skin.geometry) == dict(scene.skin.geometry)
    assert again.to_dict() == scene.to_dict()
    text = scene.to_toml_string().replace("angle = 2.6179938779914944", 'angle = "150 deg"')
    assert dict(Scene.from_toml_string(text).skin.geometry)["angle"] == pytest.approx(np.radians(150))


def test_demo_command_on_a_forearm_writes_a_png(tmp_path, capsys):
    assert main(["demo", "--skin", "forearm", "--output", str(tmp_path / "forearm.png")]) == 0
    assert "forearm" in capsys.readouterr().out
    assert (tmp_path / "forearm.png").stat().st_size > 10_000


def test_a_saved_curved_simulation_is_reconstructed_from_its_file(tmp_path):
    """The file carries the reconstruction mesh's geometry; `de.reconstruct` images it with its
    defaults, and the touch's image peaks near the touch (measured: 4 mm off on a 40 mm forearm)."""
    path = de.simulate(forearm_scene(), progress=False).save(tmp_path / "forearm.h5")
    recording = de.io.read_frames(path)
    assert recording.geometry["kind"] == "cylinder_patch"
    out = de.reconstruct(recording, progress=False)
    mesh = de.io.mesh_from_geometry(recording.geometry)
    pressed = int(np.argmax(np.abs(out.images).max(axis=1)))
    peak = mesh.element_centroids[np.argmin(out.images[pressed])]
    assert np.linalg.norm(peak - np.array(CENTRE)) < 0.01, (peak, CENTRE)


def test_touches_on_a_forearm_are_read_as_points_on_its_surface():
    """A simulated recording (the truth on its finer mesh, the reconstruction mesh's geometry)
    calibrated from its reference (one frame: no noise, so the voltage test is the subspace
    one), imaged at the calibration and read: the pressed frames each give a touch, the
    strongest a point on the meshed cylinder near the press (measured 1.2-1.9 mm off
    on a 40 mm forearm, 1.3-1.7% inside the cylinder: its triangles' planes are chords), the
    others none."""
    recording = de.simulate(forearm_scene(), progress=False).to_recording()
    calibration = de.calibrate(recording)
    images = de.reconstruct(recording, calibration=calibration, progress=False)
    found = de.touches(images, calibration)
    pressed = np.isin(np.arange(recording.n_frames), [3, 4, 5, 6])  # held from 0.3 s to 0.7 s, 10 frames a second
    assert np.all(found.count[pressed] >= 1) and np.all(found.count[~pressed] == 0), found.count
    points = found.position[pressed, 0]
    assert found.position.shape[-1] == 3
    np.testing.assert_allclose(np.hypot(points[:, 0], points[:, 1]), RHO, rtol=0.025)  # on the surface
    assert np.max(np.linalg.norm(points - np.array(CENTRE), axis=1)) < 0.004, points
    mesh = images.mesh
    errors = [de.metrics.position_error(mesh, images.images[t], CENTRE) for t in np.flatnonzero(pressed)]
    assert max(errors) < 0.004, errors  # measured 1.3-2.0 mm: the half-amplitude centroid, onto the surface
    with pytest.raises(ValueError, match=r"centre must be one point \(x, y, z\)"):
        de.metrics.position_error(mesh, images.images[4], CENTRE[:2])
    frame = int(np.flatnonzero(pressed)[0])
    assert found.lines(frame)[0].startswith("touch 0: (") and found.lines(frame)[0].split(")")[0].count(",") == 2
    presses = de.io.Presses(np.array([CENTRE[:2]]), 0.012, [0.5])  # a curved skin's presses are points in 3D
    with pytest.raises(ValueError, match=r"presses have 2-dimensional centres; the mesh's nodes have 3"):
        de.calibrate(recording, presses)
