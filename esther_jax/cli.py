"""The `esther` command line (thin: parse, call the library, print)."""

import argparse
import pathlib
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="esther", description="ESTHER: metric 3D hands from egocentric stereo (JAX)")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser("demo", help="run the main job on the embedded default (built-in hand model)")
    demo.add_argument("--out", default="esther_demo", help="output folder (default: ./esther_demo)")
    demo.add_argument("--seed", type=int, default=0)
    evaluate = commands.add_parser("evaluate", help="compare label folders with ground truth; write metrics, tables, figures")
    evaluate.add_argument("--pred", required=True, help="folder of predicted labels (<clip>/hands/<side>/labels.npz)")
    evaluate.add_argument("--gt", required=True, help="folder of clips with ground truth (<clip>/hands/<side>/gt.npz)")
    evaluate.add_argument("--out", default="evaluation", help="output folder (default: ./evaluation)")
    evaluate.add_argument("--method", default="prediction", help="method name for the tables")
    evaluate.add_argument("--seed", type=int, default=0, help="bootstrap seed")
    args = parser.parse_args(argv)
    if args.command == "demo":
        from .demo import run

        run(args.out, seed=args.seed)
    elif args.command == "evaluate":
        from .eval import evaluate_folders

        try:
            result = evaluate_folders(args.pred, args.gt, args.out, method=args.method, seed=args.seed)
        except ValueError as err:  # bad folders or files: say what, no traceback
            print(f"esther evaluate: {err}", file=sys.stderr)
            return 2
        print((pathlib.Path(args.out) / "table.md").read_text())
        print(f"{result['num_hands']} hands, coverage {result['coverage']:.1%}; wrote {pathlib.Path(args.out).resolve()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
