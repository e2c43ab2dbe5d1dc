"""The commands' argparse pieces: a parser whose help is the command's docstring, and types
for numbers with bounds, so every command refuses bad values alike.

``parser.add_argument('--rate', type=number(above=0))`` refuses ``0``, ``nan`` and
``fast`` with a message naming the value and the allowed range.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

__all__ = ['command_parser', 'non_negative_float', 'number', 'positive_float']


def command_parser(prog: str, doc: str, epilog_from: int = 1) -> argparse.ArgumentParser:
    """A parser whose ``--help`` is the command module's docstring: its first paragraph on
    one line as the description, the paragraphs from ``epilog_from`` on (past a usage block,
    say) as the epilog, laid out as written."""
    parts = doc.split('\n\n')
    return argparse.ArgumentParser(
        prog=prog, description=parts[0].replace('\n', ' ').replace('``', ''),
        epilog='\n\n'.join(parts[epilog_from:]),
        formatter_class=argparse.RawDescriptionHelpFormatter)


def number(above: float | None = None, at_least: float | None = None,
           at_most: float | None = None, unit: str = '') -> Callable[[str], float]:
    """A type accepting finite numbers ``> above`` / ``>= at_least`` / ``<= at_most``."""
    bounds = []
    if above is not None:
        bounds.append(f'> {above:g}')
    if at_least is not None:
        bounds.append(f'>= {at_least:g}')
    if at_most is not None:
        bounds.append(f'<= {at_most:g}')
    allowed = 'a finite number' + (' ' + ' and '.join(bounds) if bounds else '') + \
        (f' {unit}' if unit else '')

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
        if not math.isfinite(value) or (above is not None and not value > above) or \
                (at_least is not None and value < at_least) or \
                (at_most is not None and value > at_most):
            raise argparse.ArgumentTypeError(f"'{text}' must be {allowed}")
        return value

    parse.__name__ = 'number'
    return parse


positive_float = number(above=0.0)
non_negative_float = number(at_least=0.0)
