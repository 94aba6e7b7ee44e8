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


def test_the_benchmarks_run_on_both_legs_with_a_device_option() -> None:
    text = SCRIPT.read_text(encoding="utf-8")
    assert "the benchmark has no device option yet" not in text
    assert "for bench in bench_filter bench_point_mass bench_navigator; do" in text
    assert '"benchmarks/$bench.py" "${size[@]}" --device cpu)' in text
    assert '"benchmarks/$bench.py" "${size[@]}" --device "$GPU")' in text


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")
@pytest.mark.parametrize("bench", ["bench_filter", "bench_point_mass", "bench_navigator"])
def test_a_benchmark_asked_for_cuda_without_it_refuses_with_one_error_line(
        bench: str, tmp_path: Path) -> None:
    import sys

    script = SCRIPT.parent / f"{bench}.py"
    done = subprocess.run([sys.executable, str(script), "--quick", "--device", "cuda",
                           "--out", str(tmp_path / "runs")], capture_output=True, text=True,
                          check=False, timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --device cuda")
    assert not (tmp_path / "runs").exists()  # nothing written
