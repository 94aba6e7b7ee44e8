"""The docs' "The filter API" example (docs/guides/filter-api.md) runs as printed (on small
inputs)."""

from __future__ import annotations

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[2] / "docs" / "guides" / "filter-api.md"


def _filter_api_block() -> str:
    text = README.read_text()
    section = text[text.index("# The filter API"):]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match is not None, "no python block under 'The filter API'"
    return match.group(1)


def test_readme_filter_api_example_runs() -> None:
    n = 5
    gen = torch.Generator().manual_seed(0)
    namespace = {
        "x0": torch.zeros(n, 2, dtype=torch.float64),
        "P0": torch.eye(2, dtype=torch.float64) * 100.0,
        "F": torch.eye(2, dtype=torch.float64),
        "Q": torch.eye(2, dtype=torch.float64),
        "residual": torch.randn(n, 1, generator=gen, dtype=torch.float64) * 3.0,
        "H": torch.randn(n, 1, 2, generator=gen, dtype=torch.float64),
        "R": torch.tensor([[9.0]], dtype=torch.float64),
        "on_map": torch.ones(n, dtype=torch.bool),
        "quality": torch.tensor([[5.0, 800.0, 1.0]] * n, dtype=torch.float64),
    }
    exec(compile(_filter_api_block(), str(README), "exec"), namespace)  # noqa: S102
    assert torch.isfinite(namespace["ekf"].P).all()
