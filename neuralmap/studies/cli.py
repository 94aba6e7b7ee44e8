"""The evaluate command: ``python evaluate.py --config configs/<study>.yaml`` (``neuralmap-evaluate``).

The config's ``study:`` key (or ``--study``) picks the study; its config dataclass defines
every other option, settable in the YAML or on the command line (jsonargparse). Without
``--config`` the study's shipped default config is used (``configs/tan.yaml`` for the
default ``tan`` study). Every run writes ``<runs_dir>/<experiment>/version_<N>/`` with
report.md, results.json, PNG plots, TensorBoard events and the config.yaml used, published
only when complete; the last line printed is that folder.

Exit codes: 0 success, 2 bad input (message on stderr, no traceback), 130 interrupted
(Ctrl-C or SIGTERM; nothing written, the staging folder removed; a folder left by a
SIGKILL is removed by the next run into the same experiment).
"""

from __future__ import annotations

import re
import signal
import sys
from dataclasses import fields
from pathlib import Path
from typing import Any

import torch
import yaml
from jsonargparse import ActionConfigFile, ArgumentError, ArgumentParser, set_loader

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import check_writable_dir, load_yaml
from neuralmap.outputs import StudyOutputs
from neuralmap.resources import config_file
from neuralmap.studies.registry import STUDIES, get_study

__all__ = ["build_parser", "main", "parse_config", "run_study"]

PROG = "evaluate.py"
set_loader("yaml", load_yaml, exceptions=(yaml.YAMLError,))


def _config_paths(args: list[str]) -> list[str]:
    paths = []
    for i, arg in enumerate(args):
        if arg == "--config" and i + 1 < len(args):
            paths.append(args[i + 1])
        elif arg.startswith("--config="):
            paths.append(arg.split("=", 1)[1])
    return paths


def _study_name(args: list[str]) -> str:
    """The study named by ``--study`` or by the last ``--config`` file's ``study:`` key."""
    for i, arg in enumerate(args):
        if arg == "--study" and i + 1 < len(args):
            return args[i + 1]
        if arg.startswith("--study="):
            return arg.split("=", 1)[1]
    name = "tan"
    for path in _config_paths(args):
        file = Path(path)
        if not file.is_file():
            raise NeuralMapError(
                f"--config {path}: file not found. Pass a YAML file such as "
                f"configs/tan.yaml (studies: {', '.join(sorted(STUDIES))})."
            )
        try:
            data = load_yaml(file.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
            raise NeuralMapError(f"--config {path}: cannot read the YAML ({exc}).") from exc
        if data is None:
            raise NeuralMapError(f"--config {path}: the file is empty.")
        if not isinstance(data, dict):
            raise NeuralMapError(f"--config {path}: expected a mapping of options at the top.")
        name = str(data.get("study", name))
    return name


def build_parser(study: str = "tan") -> ArgumentParser:
    """The parser of one study: ``--config`` YAML plus every field of its config class."""
    config_cls, _, spec = get_study(study)
    default = config_file(spec.default_config)
    parser = ArgumentParser(
        prog=PROG,
        description=f"{spec.description} (study '{study}'; other studies: "
        f"{', '.join(s for s in sorted(STUDIES) if s != study)}).",
        default_config_files=[str(default)] if default.is_file() else None,
        exit_on_error=False,  # parse errors become one error line (parse_config)
    )
    parser.add_argument("--config", action=ActionConfigFile, help="YAML configuration file.")
    parser.add_class_arguments(config_cls, nested_key=None, as_group=False)
    return parser


def parse_error_line(exc: BaseException) -> str:
    """A jsonargparse parse error as one line naming the option (``--seed``, not
    ``Parser key "seed"``) and where to look up its type."""
    text = " ".join(str(exc).split())
    text = re.sub(r'Parser key "([\w.]+)":?', lambda m: f"--{m.group(1)}:", text)
    return f"{text} Run {PROG} --help for every option and its type."


def parse_config(args: list[str] | None = None) -> Any:
    """Parses and validates the options of the study the arguments name.

    Returns:
        The validated study config dataclass.

    Raises:
        NeuralMapError: Unknown study or invalid values.
        SystemExit: ``--help``, ``--print_config`` or a jsonargparse parse error.
    """
    args = list(sys.argv[1:] if args is None else args)
    study = _study_name(args)
    config_cls, _, _ = get_study(study)
    try:
        namespace = build_parser(study).parse_args(args)
    except ArgumentError as exc:
        raise NeuralMapError(parse_error_line(exc)) from None
    values = {f.name: namespace[f.name] for f in fields(config_cls) if f.name in namespace}
    values["study"] = study
    config = config_cls(**values)
    config.validate()
    return config


def run_study(config: Any) -> Path:
    """Runs a validated study config and publishes its run folder.

    Returns:
        ``<runs_dir>/<experiment>/version_<N>``.
    """
    _, run, spec = get_study(config.study)
    root = check_writable_dir(config.runs_dir) / config.experiment
    print(f"{config.study}: seed "
          + (f"{config.seed}" if config.seed is not None else "of the scenario")
          + f" (rerun with the same --seed and config to reproduce); results into {root}",
          flush=True)
    with StudyOutputs(root, config=config, title=spec.description,
                      tensorboard=config.tensorboard) as outputs:
        run(config, outputs)
        return outputs.finalize()


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _terminate_as_interrupt() -> Any:
    """Makes SIGTERM (``kill``) end the study like Ctrl-C, so that its staging folder is
    removed; returns the previous handler (None off the main thread, where signals
    cannot be handled)."""
    try:
        return signal.signal(signal.SIGTERM, _raise_interrupt)
    except ValueError:  # not the main thread
        return None


def main(args: list[str] | None = None) -> int:
    """Command-line entry point (``evaluate.py`` and the ``neuralmap-evaluate`` script).

    Args:
        args: Arguments (``None`` = ``sys.argv[1:]``).

    Returns:
        0 on success, 2 on bad input, 130 when interrupted, or the exit code of ``--help``
        / a parse error.
    """
    previous_threads = torch.get_num_threads()
    previous_term = _terminate_as_interrupt()
    try:
        config = parse_config(args)
        if config.threads is not None:
            torch.set_num_threads(config.threads)
        out_dir = run_study(config)
    except NeuralMapError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; nothing was written.", file=sys.stderr)
        return 130
    except SystemExit as exc:  # --help, --print_config, jsonargparse parse errors
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    finally:
        torch.set_num_threads(previous_threads)
        if previous_term is not None:
            signal.signal(signal.SIGTERM, previous_term)
    print(f"results written to {out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
