"""The ``diffcam`` command line. Lengths take units (``25mm``, ``3.45um``, ``532nm``)."""

from __future__ import annotations

import argparse
import sys

from .errors import DiffcamError
from .units import parse_length


def _length(name):
    def convert(text):
        try:
            return parse_length(text, name=name)
        except DiffcamError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    convert.__name__ = name
    return convert


def _cmd_demo(args) -> int:
    from .demo import run_demo

    run_demo(args.out, n=args.size)
    return 0


def _cmd_plan(args) -> int:
    from .sampling import plan_sampling

    print(plan_sampling(args.wavelength, args.pixel, args.n, args.z1, args.z2,
                        args.aperture_radius, max_offset=args.max_offset))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="diffcam",
        description="Differentiable wave optics for lensless diffuser cameras.")
    sub = parser.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="run the built-in demonstration and write a report",
                          description="Run the built-in demonstration on built-in data and "
                                      "write PNG figures and metrics.json to a folder.")
    demo.add_argument("-o", "--out", default="diffcam-report", help="report folder")
    demo.add_argument("--size", type=int, default=1024, help="simulation grid (samples/side)")
    demo.set_defaults(func=_cmd_demo)

    plan = sub.add_parser("plan", help="check the sampling of a diffuser-camera geometry",
                          description="Report Fresnel numbers, point-source chirp sampling, "
                                      "propagator validity and padding before simulating.")
    plan.add_argument("--wavelength", type=_length("wavelength"), default=532e-9)
    plan.add_argument("--pixel", type=_length("pixel"), required=True, help="grid pitch")
    plan.add_argument("--n", type=int, required=True, help="samples per side")
    plan.add_argument("--z1", type=_length("z1"), required=True, help="smallest source depth")
    plan.add_argument("--z2", type=_length("z2"), required=True, help="diffuser to sensor")
    plan.add_argument("--aperture-radius", type=_length("aperture-radius"), required=True)
    plan.add_argument("--max-offset", type=_length("max-offset"), default=0.0,
                      help="largest lateral source offset")
    plan.set_defaults(func=_cmd_plan)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except DiffcamError as e:
        print(f"diffcam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"diffcam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
