"""YAML with YAML 1.2 numbers: ``1.0e20``, ``9e0`` and ``1e-3`` read as floats.

PyYAML implements YAML 1.1, whose float pattern needs a dot and a signed exponent, so
``1.0e20`` and ``9e0`` come back as *strings* from :func:`yaml.safe_load` and a config
check then says "must be a number, got '1.0e20'". :class:`NumberSafeLoader` is
``yaml.SafeLoader`` with the float resolver widened to the YAML 1.2 core-schema floats
(optional dot, unsigned exponent), plus ``.inf``/``.nan``. Everything else (ints, bools,
strings, timestamps) resolves as in ``safe_load``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

from neuralmap.exceptions import NeuralMapError

#: YAML 1.2 core-schema float (with 1.1's ``_`` digit separators kept out) and inf/nan.
FLOAT_PATTERN = re.compile(
    r"""^(?:[-+]?(?:[0-9][0-9]*\.[0-9]*|\.[0-9]+|[0-9]+)(?:[eE][-+]?[0-9]+)
        |[-+]?(?:[0-9][0-9]*\.[0-9]*|\.[0-9]+)
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
    re.VERBOSE,
)


class NumberSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that reads ``1.0e20``, ``9e0``, ``1e-3`` as floats."""


# Copy the resolver table so yaml.SafeLoader itself is left untouched.
NumberSafeLoader.yaml_implicit_resolvers = {
    key: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:float"]
    for key, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
NumberSafeLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float", FLOAT_PATTERN, list("-+0123456789.")
)


def load_yaml(source: str | Path, *, where: str | None = None) -> Any:
    """Parses YAML text, or a ``.yaml`` file given as a :class:`Path`, with YAML 1.2 floats.

    Args:
        source: YAML text (``str``) or a file path (``Path``).
        where: Name of the source for error messages (default: the path or "YAML text").

    Returns:
        The parsed document (``None`` for an empty document: callers decide whether empty
        is allowed).

    Raises:
        NeuralMapError: Unreadable file or invalid YAML (with the line and column).
    """
    if isinstance(source, Path):
        label = where or f"YAML file '{source}'"
        try:
            text = source.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise NeuralMapError(f"{label} could not be read ({exc}).") from None
    else:
        label, text = where or "YAML text", source
    try:
        return yaml.load(text, Loader=NumberSafeLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise NeuralMapError(f"{label}: invalid YAML{at}: {problem}.") from None


__all__ = ["FLOAT_PATTERN", "NumberSafeLoader", "load_yaml"]
