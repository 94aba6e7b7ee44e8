"""The documentation: strict site build, stamped results pages, summary.md of every study
run, and ``python -m neuralmap.docs update``."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from neuralmap.docs import check_page, config_sha256, read_stamp, update_page
from neuralmap.docs.__main__ import main as docs_main
from neuralmap.docs.stamp import TINY_NOTE, RunStamp
from neuralmap.docs.trace import check_study_page, untraced_numbers
from neuralmap.outputs import SUMMARY_MARK, StudyOutputs

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "docs" / "results"
README = REPO / "README.md"


@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None
                    or importlib.util.find_spec("mkdocstrings") is None,
                    reason="mkdocs / mkdocstrings not installed (pip install -e '.[docs]')")
def test_site_builds_strictly(tmp_path: Path) -> None:
    """A broken link, a page missing from the nav or an unresolved API reference fails."""
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
        cwd=REPO, capture_output=True, text=True, timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-4000:]
    assert (tmp_path / "site" / "index.html").is_file()
    assert (tmp_path / "site" / "api" / "filters.html").read_text().count("BatchedEKF") > 3


def _result_pages() -> list[Path]:
    return sorted(p for p in RESULTS.glob("*.md") if p.name != "index.md")


def test_every_results_page_carries_a_stamp_matching_the_repository_config() -> None:
    pages = _result_pages()
    assert pages, "docs/results/ holds no results page"
    problems = [problem for page in pages for problem in check_page(page, REPO)]
    assert not problems, "\n".join(problems)


def test_docs_pages_name_no_issue_numbers() -> None:
    """The pages speak of the toolkit and the papers, not of the tracker."""
    pattern = re.compile(r"\bissues?\s*#?\s*\d+|(?<![\w&/])#\d{1,4}\b", re.IGNORECASE)
    for page in [README, *sorted((REPO / "docs").rglob("*.md"))]:
        found = pattern.search(page.read_text(encoding="utf-8"))
        assert found is None, f"{page}: {found.group(0)!r}"


def test_readme_fits_on_a_screen_and_keeps_the_ci_test_command() -> None:
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 250
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    test_command = next(line for line in ci.splitlines() if "pytest" in line).strip()
    test_command = test_command.replace("python -m pip install --quiet", "pip install")
    assert test_command in README.read_text(encoding="utf-8"), test_command


# ----------------------------------------------------------------------------- stamps
def _stamped(tmp_path: Path, config_text: str, body: str = "", **kw: object) -> Path:
    configs = tmp_path / "configs"
    configs.mkdir(exist_ok=True)
    (configs / "wind_tiny.yaml").write_text(config_text)
    stamp = RunStamp(study="wind", config="configs/wind_tiny.yaml",
                     config_sha256=config_sha256(configs / "wind_tiny.yaml"), seed=0,
                     commit="0" * 40, dirty=False, date="2026-01-01T00:00:00Z", **kw)
    page = tmp_path / "wind.md"
    page.write_text(stamp.line() + "\n# Results\n" + body)
    return page


def test_a_page_without_a_stamp_fails(tmp_path: Path) -> None:
    page = tmp_path / "tan.md"
    page.write_text("# Results\n\n| method | RMSE |\n|---|---|\n| neural | 20.9 |\n")
    assert read_stamp(page) is None
    (problem,) = check_page(page, tmp_path)
    assert "no run stamp" in problem


def test_a_stamp_whose_config_changed_fails(tmp_path: Path) -> None:
    page = _stamped(tmp_path, "study: wind\nn_runs: 6\n", TINY_NOTE)
    assert check_page(page, tmp_path) == []
    (tmp_path / "configs" / "wind_tiny.yaml").write_text("study: wind\nn_runs: 7\n")
    (problem,) = check_page(page, tmp_path)
    assert "hashes to" in problem and "rerun" in problem


def test_a_tiny_stamp_must_say_so_and_name_its_study(tmp_path: Path) -> None:
    page = _stamped(tmp_path, "study: wind\nn_runs: 6\n", "no warning here")
    assert any("does not say so" in p for p in check_page(page, tmp_path))
    page = _stamped(tmp_path, "study: tan\n", TINY_NOTE)
    assert any("names another" in p for p in check_page(page, tmp_path))
    (tmp_path / "configs" / "wind_tiny.yaml").unlink()
    assert "not in the repository" in check_page(page, tmp_path)[0]


def test_a_damaged_stamp_is_named(tmp_path: Path) -> None:
    page = tmp_path / "wind.md"
    page.write_text('<!-- neuralmap-stamp: {"study": "wind" -->\n')
    (problem,) = check_page(page, tmp_path)
    assert "line 1: damaged run stamp" in problem


# ----------------------------------------------------------------------------- traced numbers
def test_every_study_page_quotes_only_numbers_of_its_stamped_page() -> None:
    pages = sorted(p for p in (REPO / "docs" / "studies").glob("*.md") if p.name != "index.md")
    assert len(pages) >= 9
    problems = [problem for page in pages for problem in check_study_page(page, REPO)]
    assert not problems, "\n".join(problems)


def test_benchmarks_training_and_data_pages_quote_only_numbers_of_their_stamped_pages() -> None:
    from neuralmap.docs.trace import TRACED_PAGES, check_linked_page, linked_results

    pages = [p for pattern in TRACED_PAGES for p in sorted((REPO / "docs").glob(pattern))]
    assert {"benchmarks.md", "data.md", "index.md", "latent.md", "region.md"} <= {
        p.name for p in pages}
    problems = [problem for page in pages for problem in check_linked_page(page, REPO)]
    assert not problems, "\n".join(problems)
    for name in ("benchmarks.md", "data.md", "training/index.md", "training/region.md"):
        page = REPO / "docs" / name
        assert linked_results(page, REPO / "docs"), f"{name} links no stamped page"
        assert "Measured by hand at the stated size" not in page.read_text(encoding="utf-8")


def test_an_untraced_number_is_named_and_code_spans_are_not_checked() -> None:
    stamped = "| neural | 20.9 | 1.16x |"
    assert untraced_numbers("RMSE 20.9 m, 1.16× the PCRB", [stamped]) == []
    assert untraced_numbers("RMSE 21.3 m and 21.3 m, 20.9 m", [stamped]) == ["21.3"]
    assert untraced_numbers("the quantile `0.99999`, runs 1000, σ0 3 km", [stamped]) == []
    assert untraced_numbers("```\nnice 0.5\n```\nversion 2.13.0", [stamped]) == []


def test_a_study_page_without_a_stamped_page_or_with_a_hand_number_fails(
        tmp_path: Path) -> None:
    studies = tmp_path / "docs" / "studies"
    studies.mkdir(parents=True)
    page = studies / "wind.md"
    page.write_text("Wind RMSE 1.43 m/s.\n")
    (problem,) = check_study_page(page, tmp_path)
    assert "no stamped results page" in problem
    (tmp_path / "docs" / "results").mkdir()
    (tmp_path / "docs" / "results" / "wind.md").write_text("| KF | 1.431 |\n")
    (problem,) = check_study_page(page, tmp_path)
    assert "1.43 not on the stamped page" in problem
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "wind.yaml").write_text("sigma: 1.43\n")
    assert check_study_page(page, tmp_path) == []



def test_a_bound_is_not_traced_but_a_result_beside_it_is() -> None:
    stamped = "| tracker | 1.157 |"
    text = "1.157× the PCRB (target 1.10×, ≤ 1.05× map-aware; Targets: 2.5); 1.16"
    assert untraced_numbers(text, [stamped]) == ["1.16"]
    assert untraced_numbers("1.157 (≥ 90.0 % in band, < 0.5 m, > 3.3 s)", [stamped]) == []
    assert untraced_numbers("about 1.10× the bound", [stamped]) == ["1.10"]


def test_a_study_page_may_quote_a_stamped_page_it_links(tmp_path: Path) -> None:
    studies, results = tmp_path / "docs" / "studies", tmp_path / "docs" / "results"
    studies.mkdir(parents=True)
    results.mkdir()
    (results / "tan.md").write_text("| tracker | 1.157 |\n")
    page = studies / "tan.md"
    page.write_text("jacksboro 1.157; synthetic 1.412 ([run](../results/tan_synthetic.md))\n")
    (results / "tan_synthetic.md").write_text("| tracker | 1.412 |\n")  # no stamp
    problems = check_study_page(page, tmp_path)
    assert any("tan_synthetic.md, which carries no run stamp" in p for p in problems)
    assert any("1.412 not on the stamped page" in p for p in problems)
    stamp = RunStamp(study="tan", config="configs/tan_synthetic.yaml", config_sha256="0" * 64,
                     seed=0, commit="0" * 40, dirty=False, date="2026-12-03T00:00:00Z",
                     overrides={})
    (results / "tan_synthetic.md").write_text(stamp.line() + "\n| tracker | 1.412 |\n")
    assert check_study_page(page, tmp_path) == []


# ----------------------------------------------------------------------------- summary.md
@dataclass
class _Config:
    study: str = "wind"
    experiment: str = "docs_test"
    seed: int = 3


def _publish(root: Path) -> Path:
    with StudyOutputs(root, config=_Config(), title="A study", echo=False,
                      tensorboard=False) as outputs:
        outputs.add_text("Intro.")
        outputs.add_table("Headline", ["method", "RMSE [m]"], [["a", 1.5], ["b", 2.25]])
        outputs.add_table("Second", ["x"], [[1]])
        outputs.add_claim("SEEDS 002", "a claim", "1.5 m", "holds")
        return outputs.finalize()


def test_every_run_writes_a_summary_with_its_headline_table_claims_and_provenance(
        tmp_path: Path) -> None:
    run = _publish(tmp_path / "runs")
    text = (run / "summary.md").read_text()
    first, _, body = text.partition("\n")
    assert first.startswith(SUMMARY_MARK)
    provenance = json.loads(first[len(SUMMARY_MARK):].removesuffix("-->"))
    assert provenance["seed"] == 3 and provenance["study"] == "wind"
    assert provenance["date"].endswith("Z")
    assert set(provenance) == {"study", "experiment", "seed", "commit", "dirty", "date",
                               "wall_s", "machine"}
    assert 0 <= provenance["wall_s"] < 60 and provenance["machine"]["cores"] >= 1
    assert f"Study time: {provenance['wall_s']} s wall on" in body
    assert "## Headline" in body and "| b | 2.25 |" in body
    assert "Second" not in body  # only the headline table
    assert "| SEEDS 002 | a claim | 1.5 m | **holds** |" in body


def test_a_study_can_name_its_headline_table(tmp_path: Path) -> None:
    with StudyOutputs(tmp_path, config=_Config(), title="A study", echo=False,
                      tensorboard=False) as outputs:
        outputs.add_table("First", ["x"], [[1]])
        outputs.add_table("Navigation", ["method", "RMSE [m]"], [["a", 2.0]], headline=True)
        text = (outputs.finalize() / "summary.md").read_text()
    assert "## Navigation" in text and "| a | 2 |" in text and "First" not in text


def _wind_tiny_run(tmp_path: Path, **override: object) -> Path:
    """A run folder as evaluate.py writes it for configs/wind_tiny.yaml (its resolved
    config), without running the study."""
    from dataclasses import asdict

    from neuralmap.io import to_jsonable
    from neuralmap.studies.cli import parse_config

    run = _publish(tmp_path / "runs")
    config = to_jsonable(asdict(parse_config(
        ["--config", str(REPO / "configs" / "wind_tiny.yaml")])))
    config.update(runs_dir="/somewhere/else", **override)  # where a run reports: ignored
    (run / "config.yaml").write_text(yaml.safe_dump(config))
    return run


def test_update_stamps_the_run_with_its_config_and_lists_overrides(tmp_path: Path) -> None:
    run = _wind_tiny_run(tmp_path)
    (run / "fig.png").write_bytes(b"\x89PNG fake")
    page = update_page(run, docs_dir=tmp_path / "docs", configs_dir=REPO / "configs")
    assert page == tmp_path / "docs" / "results" / "wind.md"
    stamp = read_stamp(page)
    assert stamp is not None and stamp.config == "configs/wind_tiny.yaml"
    assert stamp.config_sha256 == config_sha256(REPO / "configs" / "wind_tiny.yaml")
    assert stamp.seed == 3 and stamp.overrides == {} and stamp.tiny
    text = page.read_text()
    assert TINY_NOTE in text and "| b | 2.25 |" in text and "### Headline" in text
    assert "| machine |" in text and "Study time:" in text
    assert (tmp_path / "docs" / "results" / "wind" / "fig.png").is_file()
    assert check_page(page, REPO) == []

    shutil.rmtree(tmp_path / "runs")
    run = _wind_tiny_run(tmp_path, n_runs=7)
    stamp = read_stamp(update_page(run, docs_dir=tmp_path / "docs",
                                   configs_dir=REPO / "configs", figures=False))
    assert stamp is not None and stamp.overrides == {"n_runs": 7}
    assert "--n_runs 7" in (tmp_path / "docs" / "results" / "wind.md").read_text()



def test_a_run_of_another_config_of_the_study_gets_that_config_s_page(tmp_path: Path) -> None:
    from dataclasses import asdict

    from neuralmap.io import to_jsonable
    from neuralmap.studies.cli import parse_config

    @dataclass
    class _Tan(_Config):
        study: str = "tan"

    with StudyOutputs(tmp_path / "runs", config=_Tan(), title="TAN", echo=False,
                      tensorboard=False) as outputs:
        outputs.add_table("Headline", ["method", "RMSE [m]"], [["tracker", 76.9]])
        run = outputs.finalize()
    config = to_jsonable(asdict(parse_config(
        ["--config", str(REPO / "configs" / "tan_synthetic.yaml")])))
    (run / "config.yaml").write_text(yaml.safe_dump(config))
    page = update_page(run, docs_dir=tmp_path / "docs", configs_dir=REPO / "configs")
    assert page == tmp_path / "docs" / "results" / "tan_synthetic.md"
    stamp = read_stamp(page)
    assert stamp is not None and stamp.config == "configs/tan_synthetic.yaml"
    assert stamp.study == "tan" and not stamp.tiny and check_page(page, REPO) == []


def test_update_refuses_a_folder_that_is_not_a_run(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    for target in (tmp_path / "missing", tmp_path / "empty"):
        assert docs_main(["update", str(target), "--docs_dir", str(tmp_path / "docs")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ")
    assert "summary.md" in err[0]
    assert not (tmp_path / "docs").exists()  # nothing written


def test_every_study_is_in_the_studies_table() -> None:
    from neuralmap.studies.registry import STUDIES

    table = (REPO / "docs" / "studies" / "index.md").read_text(encoding="utf-8")
    missing = [name for name in STUDIES if f"[`{name}`](" not in table]
    assert not missing, f"docs/studies/index.md lacks {missing}"


# ----------------------------------------------------------------------------- benchmarks, training
def _fake_bench(root: Path, body: str = "print('x')\n") -> Path:
    script = root / "benchmarks" / "bench_fake.py"
    script.parent.mkdir(parents=True, exist_ok=True)
    script.write_text(body)
    return script


def test_benchmark_output_becomes_markdown_tables_and_text_blocks() -> None:
    from neuralmap.docs.bench_run import markdown_of_output

    out = markdown_of_output("# head 1.5\n\n| a | b |\n|---|---:|\n| x | 2.25 |\ntail 3.5\n")
    assert out == ("```text\n# head 1.5\n```\n\n| a | b |\n|---|---:|\n| x | 2.25 |\n\n"
                   "```text\ntail 3.5\n```\n")


def test_a_benchmark_run_is_stamped_and_goes_stale_when_its_script_changes(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    from neuralmap.docs.bench_run import script_sha256, start_bench

    script = _fake_bench(tmp_path)
    args = argparse.Namespace(n=7, quick=False, out=str(tmp_path / "runs" / "bench_fake"))
    run = start_bench(script, args, ["--n", "7"])
    print("| what | rate |\n|---|---:|\n| fast | 4.271 |")
    print("note 0.125\n# a comment line")
    folder = run.finish({"rate": 4.271})
    assert folder == tmp_path / "runs" / "bench_fake" / "version_0"
    assert capsys.readouterr().out.endswith(f"stamped run: {folder}\n")
    first, _, body = (folder / "summary.md").read_text().partition("\n")
    provenance = json.loads(first[len(SUMMARY_MARK):].removesuffix("-->"))
    assert provenance["kind"] == "bench" and provenance["argv"] == ["--n", "7"]
    assert provenance["script_sha256"] == script_sha256(script)
    assert provenance["options"] == {"n": 7, "quick": False}
    assert {"cpu", "cores", "torch_threads", "load_1min"} <= set(provenance["machine"])
    assert "| fast | 4.271 |" in body and "```text\nnote 0.125\n# a comment line\n```" in body
    results = json.loads((folder / "results.json").read_text())
    assert results["results"] == {"rate": 4.271} and "note 0.125" in results["output"]
    assert not list((tmp_path / "runs" / "bench_fake").glob(".tmp-*"))  # published whole

    page = update_page(folder, docs_dir=tmp_path / "docs", configs_dir=REPO / "configs")
    assert page == tmp_path / "docs" / "results" / "bench_fake.md"
    stamp = read_stamp(page)
    assert stamp is not None and stamp.kind == "bench"
    assert stamp.config == "benchmarks/bench_fake.py"
    text = page.read_text()
    assert "| fast | 4.271 |" in text and "`python benchmarks/bench_fake.py --n 7`" in text
    assert stamp.overrides == {"n": 7, "quick": False} and "`n=7`, `quick=false`" in text
    assert "\n# a comment line\n```" in text  # code lines are not headings to demote
    warnings: list[str] = []
    assert check_page(page, tmp_path, warnings=warnings) == [] and warnings == []
    second = update_page(folder, docs_dir=tmp_path / "docs", configs_dir=REPO / "configs",
                         page_name="bench_fake_n7")  # a second run of one benchmark
    assert second.name == "bench_fake_n7.md" and read_stamp(second) == stamp
    assert docs_main(["update", str(folder), "--docs_dir", str(tmp_path / "docs"),
                      "--page", "tan"]) == 2
    assert "--page 'tan'" in capsys.readouterr().err
    script.write_text("print('y')\n")  # the benchmark changed: the page is stale, a warning
    assert check_page(page, tmp_path, warnings=warnings) == []
    (warning,) = warnings
    assert "stale" in warning and "rerun the benchmark" in warning
    script.unlink()
    assert "not in the repository" in check_page(page, tmp_path)[0]


def test_a_quick_benchmark_run_is_stamped_only_with_out(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    import argparse

    from neuralmap.docs.bench_run import start_bench

    monkeypatch.chdir(tmp_path)
    script = _fake_bench(tmp_path)
    run = start_bench(script, argparse.Namespace(quick=True, out=None), ["--quick"])
    print("smoke")
    assert run.finish() is None and not (tmp_path / "runs").exists()


def _train_run(tmp_path: Path, configs: list[Path], argv: list[str]) -> Path:
    from neuralmap.training.run_summary import write_train_summary

    run = tmp_path / "runs" / "jacksboro" / "version_0"
    run.mkdir(parents=True)
    write_train_summary(run, mode="map", argv=argv, configs=configs,
                        metrics={"rmse_m": 0.7122, "epochs": 400, "tile": "jacksboro",
                                 "tile_shape": [344, 403]}, seed=0, wall_s=309.25,
                        experiment="jacksboro")
    return run


def test_a_training_run_is_stamped_with_its_config_and_overrides(tmp_path: Path) -> None:
    run = _train_run(tmp_path, [REPO / "configs" / "train.yaml"],
                     ["--runs_dir", "/x", "--experiment", "e", "--model.lr=0.01",
                      "--trainer.max_epochs", "3"])
    summary = (run / "summary.md").read_text()
    assert summary.startswith(SUMMARY_MARK) and "| rmse_m | 0.7122 |" in summary
    assert "tile_shape" not in summary  # scalars only
    page = update_page(run, docs_dir=tmp_path / "docs", configs_dir=REPO / "configs")
    assert page.name == "train_train.md"
    stamp = read_stamp(page)
    assert stamp is not None and stamp.kind == "train" and stamp.seed == 0
    assert stamp.config == "configs/train.yaml"
    assert stamp.overrides == {"model.lr": "0.01", "trainer.max_epochs": "3"}
    text = page.read_text()
    assert ("`python train.py --config configs/train.yaml --model.lr 0.01 "
            "--trainer.max_epochs 3`") in text and "| wall_s" in text
    assert check_page(page, REPO) == []


def test_a_training_run_of_a_changed_or_unshipped_config_is_refused(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    configs = tmp_path / "configs"
    configs.mkdir()
    (configs / "train.yaml").write_text("seed_everything: 0\n")
    run = _train_run(tmp_path, [configs / "train.yaml"], [])
    (configs / "train.yaml").write_text("seed_everything: 1\n")
    args = ["update", str(run), "--docs_dir", str(tmp_path / "docs"), "--configs_dir",
            str(configs)]
    assert docs_main(args) == 2
    assert "changed since the run" in capsys.readouterr().err
    (configs / "train.yaml").unlink()
    assert docs_main(args) == 2
    assert "not a file of" in capsys.readouterr().err
    assert not (tmp_path / "docs").exists()


def test_a_number_may_be_quoted_rounded_but_not_to_one_digit() -> None:
    assert untraced_numbers("RMSE 0.71 m", ["| rmse_m | 0.7122 |"]) == ["0.71"]  # exact
    assert untraced_numbers("RMSE 0.71 m, 0.712 m", ["| rmse_m | 0.7122 |"], rounded=True) == []
    assert untraced_numbers("RMSE 0.72 m", ["| 0.7122 |"], rounded=True) == ["0.72"]
    assert untraced_numbers("about 0.7 m", ["| 0.7122 |"], rounded=True) == ["0.7"]


def test_a_linked_page_quotes_only_numbers_of_the_stamped_pages_it_links(
        tmp_path: Path) -> None:
    from neuralmap.docs.trace import check_linked_page

    docs = tmp_path / "docs"
    (docs / "results").mkdir(parents=True)
    stamp = RunStamp(study="bench_fake", config="benchmarks/bench_fake.py",
                     config_sha256="0" * 64, seed=None, commit=None, dirty=None,
                     date="2026-01-01T00:00:00Z", kind="bench")
    (docs / "results" / "bench_fake.md").write_text(stamp.line() + "\n| fast | 4.271 |\n")
    (docs / "results" / "hand.md").write_text("| slow | 9.5 |\n")
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "train.yaml").write_text("lr: 0.003\n")
    page = docs / "benchmarks.md"
    page.write_text("Fast: 4.27 M/s ([run](results/bench_fake.md)), lr 0.003 "
                    "(`configs/train.yaml`).\n")
    assert check_linked_page(page, tmp_path) == []
    page.write_text("Fast: 4.27 M/s, 4.31 M/s ([run](results/bench_fake.md#fast)).\n")
    (problem,) = check_linked_page(page, tmp_path)
    assert "4.31 on no stamped page" in problem
    page.write_text("Slow: 9.5 ([hand](results/hand.md)).\n")
    problems = check_linked_page(page, tmp_path)
    assert "carries no run stamp" in problems[0] and "9.5" in problems[1]


def test_train_py_writes_a_summary_that_update_stamps(tmp_path: Path) -> None:
    """A 1-epoch fit of a small tile: summary.md beside metrics.json, stamped with the
    default config and the options on the command line as overrides."""
    import numpy as np

    from neuralmap.training.cli import main as train_main

    tile = tmp_path / "t.npy"
    np.save(tile, np.random.default_rng(0).normal(size=(40, 40)).cumsum(0).cumsum(1))
    path = train_main(["--data.path", str(tile), "--data.spacing", "30", "--runs_dir",
                       str(tmp_path / "runs"), "--experiment", "t", "--model.block_nodes",
                       "16", "--model.hidden", "8", "--model.n_frequencies", "4",
                       "--data.refit_epochs", "0", "--trainer.max_epochs", "1",
                       "--trainer.enable_progress_bar", "false"])
    assert path is not None
    metrics = json.loads((path.parent / "metrics.json").read_text())
    page = update_page(path.parent, docs_dir=tmp_path / "docs", configs_dir=REPO / "configs",
                       figures=False)
    stamp = read_stamp(page)
    assert page.name == "train_train.md" and stamp is not None and stamp.kind == "train"
    assert stamp.config == "configs/train.yaml" and stamp.seed == 0
    assert stamp.overrides["trainer.max_epochs"] == "1" and "runs_dir" not in stamp.overrides
    assert f"| rmse_m | {metrics['rmse_m']:.4g} |" in page.read_text()
    assert check_page(page, REPO) == []


@pytest.mark.parametrize("package, page", [("neuralmap.nav", "nav.md"),
                                           ("neuralmap.flights", "flights.md")])
def test_the_product_api_pages_list_every_exported_name(package: str, page: str) -> None:
    import importlib

    text = (REPO / "docs" / "api" / page).read_text(encoding="utf-8")
    listed = set(re.findall(r"^\s+- (\w+)$", text, flags=re.M))
    blocks = re.findall(r"^::: ([\w.]+)\n((?:[ \t]+\S.*\n?)*)", text, flags=re.M)
    whole = {name for name, options in blocks if "members:" not in options}
    module = importlib.import_module(package)
    missing = [n for n in module.__all__ if n not in listed
               and getattr(getattr(module, n), "__module__", None) not in whole]
    assert not missing, f"docs/api/{page} does not list {missing} of {package}.__all__"
