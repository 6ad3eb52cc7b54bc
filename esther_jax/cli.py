"""The `esther` command line (thin: parse, call the library, print)."""

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="esther", description="ESTHER: metric 3D hands from egocentric stereo (JAX)")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser("demo", help="run the main job on the embedded default (built-in hand model)")
    demo.add_argument("--out", default="esther_demo", help="output folder (default: ./esther_demo)")
    demo.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.command == "demo":
        from .demo import run

        run(args.out, seed=args.seed)
    return 0


if __name__ == "__main__":
    sys.exit(main())
