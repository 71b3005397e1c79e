"""The `diffeit` command line."""

from __future__ import annotations

import argparse
import sys


def _demo(arguments: argparse.Namespace) -> int:
    from .demo import run_demo

    result = run_demo(arguments.output, seed=arguments.seed)
    print(
        f"data mesh {result.n_data_elements} triangles, reconstruction mesh "
        f"{result.n_reconstruction_elements} triangles\n"
        f"position error: {result.position_error:.4f} m (unit disc)\n"
        f"correlation with the truth: {result.correlation:.3f}\n"
        f"peak dsigma: {result.peak:.3e} S/sq\n"
        f"wrote {result.figure}"
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="diffeit", description="Differentiable EIT for tactile skins.")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser("demo", help="simulate a touch on a 16-electrode skin and image it")
    demo.add_argument("-o", "--output", default="demo.png", help="PNG to write (default demo.png)")
    demo.add_argument("--seed", type=int, default=0, help="noise seed")
    demo.set_defaults(run=_demo)
    arguments = parser.parse_args(argv)
    return arguments.run(arguments)


if __name__ == "__main__":
    sys.exit(main())
