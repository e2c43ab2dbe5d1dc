"""What the commands that read one map and write files beside it share: their command line
(the map, ``--config``/``--set`` for one node's section of parameters, ``--output-dir``,
``--name``, ``--up``, ``--quiet``) and the parameters it gives."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from inhand_common.cli_types import command_parser
from inhand_common.parameters import ParamSpec, load_yaml_parameters, validate
from inhand_mapping.mapping_config import parse_overrides
from inhand_tools.drawing import UP_AXES

__all__ = ['map_command_parser', 'output_of', 'print_report', 'section_parameters']


def map_command_parser(prog: str, doc: str | None, section: str) -> argparse.ArgumentParser:
    """The parser of a command on one map whose parameters are ``section`` of ROS parameter
    files."""
    parser = command_parser(prog, doc)
    parser.add_argument('map', type=Path, help='map: NPZ (or PLY) saved by occupancy/save or build_map')
    parser.add_argument('--config', action='append', default=[],
                        help=f'ROS parameter file with a {section} section; repeatable, later '
                        'files override earlier ones')
    parser.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                        help='override a parameter (repeatable)')
    parser.add_argument('--output-dir', type=Path, help="default: the map's folder")
    parser.add_argument('--name', help="file name stem (default: the map's)")
    parser.add_argument('--up', choices=sorted(UP_AXES),
                        help="the map frame's axis that points up (default: -z for a map build_map "
                        'registered in static mode, the tracker frame; else +z in the object frame)')
    parser.add_argument('--quiet', action='store_true', help='only the summary line')
    return parser


def section_parameters(configs: Sequence[str], overrides: Sequence[str], section: str,
                       specs: Sequence[ParamSpec]) -> dict[str, Any]:
    """``section`` of ``configs`` (later files win), then ``--set`` pairs, checked against
    ``specs``; ParameterError names what is refused."""
    values: dict[str, Any] = {}
    for path in configs:
        values.update(load_yaml_parameters(path, section))
    values.update(parse_overrides(list(overrides)))
    return validate(specs, values)


def output_of(args: argparse.Namespace) -> tuple[Path, str]:
    """(folder, file name stem) to write in: ``--output-dir`` and ``--name``, else the map's."""
    return (args.output_dir if args.output_dir is not None else args.map.parent,
            args.name or args.map.stem)


def print_report(prog: str, summary: str, details: Sequence[str], seconds: dict[str, float],
                 written: Sequence[Path], quiet: bool) -> None:
    """The command's summary line, then (unless ``quiet``) one line per detail and the time of
    each step, then the files written."""
    print(f'{prog}: {summary}')
    if not quiet:
        for line in details:
            print(f'  {line}')
        print('  took ' + ', '.join(f'{k} {v:.2f} s' for k, v in seconds.items()))
    print('  wrote ' + ', '.join(str(p) for p in written))
