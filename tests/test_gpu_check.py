"""benchmarks/gpu_check.sh: valid bash, and a clean refusal on a machine without CUDA."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu_check.sh"


@pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")
def test_the_script_parses() -> None:
    done = subprocess.run(["bash", "-n", str(SCRIPT)], capture_output=True, text=True,
                          check=False)
    assert done.returncode == 0, done.stderr


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
def test_without_cuda_it_refuses_with_one_error_line() -> None:
    done = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True, check=False,
                          timeout=120)
    assert done.returncode == 2
    assert done.stderr.startswith("error: no CUDA device here")
    assert "--dry-run" in done.stderr
    assert done.stdout == ""
