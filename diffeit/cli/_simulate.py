"""`diffeit simulate SCENE -o FRAMES.h5`: simulate a scene file (or a shipped example)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from ._errors import reporting_user_errors


def add_command(commands: argparse._SubParsersAction) -> None:
    """Add `simulate` to the subcommands `commands` of the `diffeit` parser."""
    from ..scene import EXAMPLES

    simulate = commands.add_parser(
        "simulate",
        help="simulate a scene (TOML file or example name) and write its frames file",
        description="Simulate every frame of a scene with the effects it declares and write a diffeit frames "
        "file (HDF5: frames, times, reference, the true conductivity on the simulation mesh, the scene). "
        f"Examples: {', '.join(EXAMPLES)}.",
    )
    simulate.add_argument("scene", help="a scene file (.toml) or the name of an example scene")
    simulate.add_argument("-o", "--output", required=True, help="frames file to write (.h5)")
    simulate.add_argument("--plot", help="also save the true conductivity change of some frames as this PNG")
    simulate.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    simulate.set_defaults(run=reporting_user_errors("simulate", _simulate_scene))


def _simulate_scene(arguments: argparse.Namespace) -> int:
    from ..scene import EXAMPLES, Scene, example, simulate

    source = Path(arguments.scene)
    if source.suffix.lower() != ".toml" and arguments.scene in EXAMPLES:
        scene = example(arguments.scene)
    else:
        scene = Scene.from_toml(source)
    output = Path(arguments.output)
    for path in (output, Path(arguments.plot) if arguments.plot else None):
        if path is not None and path.exists() and not arguments.overwrite:
            raise FileExistsError(f"{path} exists; pass --overwrite to replace it")
    simulation = simulate(scene)
    simulation.save(output, overwrite=arguments.overwrite)
    lines = [
        f"{scene.name or source.name}: {scene.n_frames} frames at {scene.frame_rate:g} Hz, "
        f"{simulation.mesh.n_elements} triangles (reconstruction mesh: h = {scene.skin.h:g} m)",
        f"stages: {', '.join(simulation.stages)}; {simulation.solves} forward solves",
        f"wrote {output}",
    ]
    if arguments.plot:
        from ..plotting import plot_image_strip

        background = np.asarray(scene.background.values_on(simulation.mesh))
        plot_image_strip(
            arguments.plot,
            simulation.mesh,
            np.asarray(simulation.truth) - background,
            times=np.asarray(simulation.times),
            title=f"{scene.name or source.name}: true conductivity change",
        )
        lines.append(f"wrote {arguments.plot}")
    print("\n".join(lines))
    return 0
