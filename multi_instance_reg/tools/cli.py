"""``mireg``: one entry point, one module per sub-command.

Each sub-command module defines ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``. Modules are imported only when their command runs, so
``mireg register`` does not pay for OpenCV or rclpy.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from ..errors import InputError

# name -> (module, one-line help)
COMMANDS = {
    "register": ("multi_instance_reg.tools.register", "multi-instance registration of a correspondence set (npz in, npz out)"),
    "build-model": ("multi_instance_reg.tools.build_model", "build the stored object model (npz) from a capture bag or colour/depth PNGs"),
    "offline": ("multi_instance_reg.tools.offline", "replay a bag through the RGB-D pipeline: poses.json, metrics.json with ground truth"),
    "bench": ("multi_instance_reg.tools.bench", "benchmarks that print figures: table1, core, ..."),
    "play": ("multi_instance_reg.tools.play", "publish a bag into the ROS graph with its original timing"),
    "demo": ("multi_instance_reg.tools.demo", "the end-to-end demo: synthetic bags, model, node, live replay, MHF1 and latency"),
    "listen": ("multi_instance_reg.tools.listen", "print the node's instances per frame; MHF1 against a bag's ground truth"),
    "synth": ("multi_instance_reg.tools.synth", "make synthetic D455 tabletop bags with ground truth (scene, capture)"),
    "bop": ("multi_instance_reg.tools.bop", "BOP datasets: run the pipeline (results CSV, overlays), build a model from "
                                            "its mesh, convert a scene to a bag"),
    "tune": ("multi_instance_reg.tools.tune", "search parameters on a labelled BOP set (Optuna, trials on Ray): params.yaml and a report"),
    "param-docs": ("multi_instance_reg.tools.param_docs", "write the parameter reference (docs/parameters.md) from the declared parameters"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mireg", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module_name)
        # Arguments are added lazily below, only for the command actually used.
    return parser


def parser_for(argv: list[str]) -> argparse.ArgumentParser:
    """The parser with the arguments of the command that argv names: its module only is
    imported (the README test parses the README's command lines with it, too)."""
    parser = build_parser()
    name = next((a for a in argv if not a.startswith("-")), None)
    if name in COMMANDS:
        module = importlib.import_module(COMMANDS[name][0])
        module.add_arguments(parser._subparsers._group_actions[0].choices[name])
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parser_for(argv).parse_args(argv)
    module = importlib.import_module(args._module)
    try:
        return int(module.run(args) or 0)
    except InputError as exc:
        print(f"mireg {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except (OSError, EOFError) as exc:
        print(f"mireg {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"mireg {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
