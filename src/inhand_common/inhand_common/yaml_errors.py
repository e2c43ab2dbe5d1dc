"""One line for a YAML syntax error: where it is and what is wrong, without PyYAML's dump."""

from __future__ import annotations

import yaml

__all__ = ['describe_yaml_error']


def describe_yaml_error(error: yaml.YAMLError) -> str:
    """``not valid YAML at line N (problem)``, for messages that name the file before it."""
    mark = getattr(error, 'problem_mark', None)
    where = f' at line {mark.line + 1}' if mark is not None else ''
    problem = getattr(error, 'problem', None) or str(error).splitlines()[0]
    return f'not valid YAML{where} ({problem})'
