"""Output files written whole or not at all: atomic writes, strict JSON, version folders.

Every writer goes through a temporary file in the destination folder and
`os.replace`, so a reader (or a crash) never sees a half-written file. Files get the
permission bits a plain ``open`` would give under the current umask (``tempfile`` alone
would leave them owner-only). Several files of one output are written all or nothing
(`atomic_files`: all to temporary names first, renamed together at the end). Run folders
are built under a hidden temporary name and published as the next free ``version_<N>``
(or in place of an earlier output: `replacing_dir`); the number is reserved with an
atomic ``mkdir`` so two concurrent runs can never take the same folder.
"""

from __future__ import annotations

import errno
import io as _io
import json
import math
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import IO, Any

import numpy as np
import yaml

from neuralmap.exceptions import NeuralMapError

__all__ = [
    "AtomicFiles",
    "atomic_files",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_figure",
    "atomic_write_json",
    "atomic_write_text",
    "atomic_write_torch",
    "check_writable_dir",
    "default_mode",
    "json_text",
    "next_version_dir",
    "publish_dir",
    "replacing_dir",
    "staging_dir",
    "to_jsonable",
    "version_number",
]

_VERSION = re.compile(r"version_(\d+)")


def default_mode(*, directory: bool = False) -> int:
    """Permission bits a plain ``open``/``mkdir`` would give under the current umask."""
    mask = os.umask(0)
    os.umask(mask)
    return (0o777 if directory else 0o666) & ~mask


def _write_temp(path: Path, write: Callable[[IO[bytes]], None]) -> str:
    """Writes a hidden temporary file beside ``path`` through ``write(handle)``.

    The low-level writer of every atomic write: the file gets the umask's permission
    bits; on any error (a full disk included) it is removed again and the error re-raised.

    Returns:
        The temporary file's path (same folder as ``path``, so `os.replace` is atomic).
    """
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            write(handle)
        os.chmod(tmp, default_mode())
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return tmp


def atomic_write(path: str | os.PathLike[str], write: Callable[[IO[bytes]], None]) -> Path:
    """Writes ``path`` through ``write(handle)`` on a temporary file, then renames it.

    Args:
        path: Destination file; its folder is created when missing.
        write: Writes the whole content into the binary handle it is given.

    Returns:
        The destination path. On any error the temporary file is removed and the
        destination is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _write_temp(path, write)
    try:
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


class AtomicFiles:
    """Several output files written all or nothing (`atomic_files`).

    Each `write` goes to a hidden temporary file in the destination's folder at once (the
    bytes are not held in memory); `commit` renames them all into place at the end. Until
    then the destinations keep their earlier content; `discard` removes the temporary
    files, and the folders this batch created when they are left empty.

    Attributes:
        option: How the messages name the output (``--out``, ``outputpath``).
    """

    def __init__(self, *, option: str = "--out") -> None:
        self.option = option
        self._pending: list[tuple[str, Path]] = []
        self._remove: list[Path] = []
        self._created: list[Path] = []

    def _folder(self, folder: Path) -> None:
        missing = [p for p in (folder, *folder.parents) if not p.exists()]
        folder.mkdir(parents=True, exist_ok=True)
        self._created.extend(missing)  # deepest first: removed in this order

    def write(self, path: str | os.PathLike[str], write: Callable[[IO[bytes]], None]) -> Path:
        """Writes ``path``'s future content to a temporary file (see `atomic_write`).

        Raises:
            NeuralMapError: The file cannot be written (a full disk, a read-only folder, a
                folder in the way), with the path, the reason and the fix.
        """
        path = Path(path)
        try:
            self._folder(path.parent)
            self._pending.append((_write_temp(path, write), path))
        except OSError as exc:
            raise self._error(path, exc) from None
        return path

    def write_bytes(self, path: str | os.PathLike[str], data: bytes) -> Path:
        """`write` of bytes."""
        return self.write(path, lambda handle: handle.write(data))

    def write_text(self, path: str | os.PathLike[str], text: str) -> Path:
        """`write` of UTF-8 text."""
        return self.write_bytes(path, text.encode("utf-8"))

    def write_json(self, path: str | os.PathLike[str], obj: Any) -> Path:
        """`write` of strict, indented JSON (as `atomic_write_json`)."""
        return self.write_text(path, json_text(obj))

    def remove(self, path: str | os.PathLike[str]) -> None:
        """Removes ``path`` (when present) at `commit`: an earlier output this run replaces
        with nothing, which would otherwise sit beside the new files as if it were theirs."""
        self._remove.append(Path(path))

    def commit(self) -> list[Path]:
        """Renames every temporary file into place, then removes the files marked with
        `remove`; returns the destinations."""
        done = []
        try:
            for tmp, path in self._pending:
                os.replace(tmp, path)
                done.append(path)
            for path in self._remove:
                if path not in done:
                    path.unlink(missing_ok=True)
        except OSError as exc:
            raise self._error(path, exc) from None
        self._pending = []
        self._created = []
        return done

    def discard(self) -> None:
        """Removes the temporary files not yet renamed and the empty folders this batch
        created; the destinations keep their earlier content."""
        for tmp, _ in self._pending:
            if os.path.exists(tmp):
                os.unlink(tmp)
        self._pending = []
        for folder in self._created:
            try:
                folder.rmdir()
            except OSError:  # not empty (another writer's files) or already gone
                continue
        self._created = []

    def _error(self, path: Path, exc: OSError) -> NeuralMapError:
        if exc.errno == errno.ENOSPC:
            fix = "the disk is full: free space or pick a folder on another disk"
        elif exc.errno == errno.EDQUOT:
            fix = "the disk quota is used up: free space or pick another folder"
        else:
            fix = "pick a writable folder"
        return NeuralMapError(
            f"{self.option}: cannot write '{path}' ({exc.strerror or exc}); {fix}. Nothing "
            "was written: earlier outputs there are unchanged.")


@contextmanager
def atomic_files(*, option: str = "--out") -> Iterator[AtomicFiles]:
    """Writes several files all or nothing.

    ``with atomic_files(option="--out") as files: files.write_bytes(a, ...);
    files.write_text(b, ...)``: every file goes to a temporary name as it is written and
    all are renamed into place when the block ends without an exception. An exception,
    Ctrl-C or a full disk in the block leaves the earlier outputs as they were, no new
    file and no temporary file (nor a folder the block created). The renames at the end
    are a few microseconds; they do not need free space.

    Raises:
        NeuralMapError: A file cannot be written (full disk, read-only folder), naming it.
    """
    files = AtomicFiles(option=option)
    try:
        yield files
        files.commit()
    finally:
        files.discard()


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Writes bytes atomically (see `atomic_write`)."""
    return atomic_write(path, lambda handle: handle.write(data))


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Writes UTF-8 text atomically (see `atomic_write`)."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def to_jsonable(value: Any) -> Any:
    """Converts tensors, numpy values and non-finite floats to strict-JSON values.

    NaN and ±inf become ``None`` (strict JSON has no NaN); tensors and arrays become
    (nested) lists; tuples and sets become lists; dataclasses become dicts; paths become
    strings; anything else its ``str``.
    """
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "detach") and hasattr(value, "cpu"):  # torch.Tensor
        return to_jsonable(value.detach().cpu().numpy())
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, Mapping):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set)):
        return [to_jsonable(v) for v in value]
    if hasattr(value, "__dataclass_fields__"):
        return to_jsonable(asdict(value))
    return str(value)


def json_text(obj: Any) -> str:
    """``obj`` as strict, indented JSON text (see `to_jsonable`), ending in a newline."""
    return json.dumps(to_jsonable(obj), indent=2, allow_nan=False, ensure_ascii=False) + "\n"


def atomic_write_json(path: str | os.PathLike[str], obj: Any) -> Path:
    """Writes ``obj`` as strict, indented JSON (see `to_jsonable`) atomically."""
    return atomic_write_text(path, json_text(obj))


def atomic_write_torch(path: str | os.PathLike[str], obj: Any) -> Path:
    """Saves ``obj`` with `torch.save` atomically."""
    import torch

    buffer = _io.BytesIO()
    torch.save(obj, buffer)
    return atomic_write_bytes(path, buffer.getvalue())


def atomic_write_figure(path: str | os.PathLike[str], fig: Any, *, dpi: int = 120) -> Path:
    """Saves a matplotlib figure as PNG atomically."""
    return atomic_write(
        path, lambda handle: fig.savefig(handle, format="png", dpi=dpi, bbox_inches="tight")
    )


def version_number(path: str | os.PathLike[str]) -> int:
    """``N`` of a ``version_N`` folder name, −1 for any other name."""
    match = _VERSION.fullmatch(Path(path).name)
    return int(match.group(1)) if match else -1


def check_writable_dir(root: str | os.PathLike[str], *, option: str = "--runs_dir") -> Path:
    """Checks, before any work, that ``root`` is (or can become) a writable folder.

    Nothing is created: the nearest existing ancestor must be a writable folder.

    Raises:
        NeuralMapError: ``root`` or one of its ancestors is a regular file, or the nearest
            existing ancestor is not writable.
    """
    root = Path(root)
    for parent in (root, *root.parents):
        if not parent.exists():
            continue
        if not parent.is_dir():
            raise NeuralMapError(
                f"{option} {root}: {parent} is a file, not a folder. Pass a folder path "
                "(it is created when missing)."
            )
        if not os.access(parent, os.W_OK | os.X_OK):
            raise NeuralMapError(
                f"{option} {root}: {parent} is not writable; pick another folder."
            )
        break
    return root


def next_version_dir(root: str | os.PathLike[str]) -> Path:
    """Reserves and creates the next free ``root/version_<N>`` (atomic ``mkdir``).

    Two processes calling this at once get different folders: the ``mkdir`` of a name
    already taken fails and the next number is tried.
    """
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    for _ in range(1000):
        existing = [version_number(p) for p in root.glob("version_*")]
        target = root / f"version_{max(existing, default=-1) + 1}"
        try:
            target.mkdir(mode=default_mode(directory=True))
        except FileExistsError:
            continue
        return target
    raise NeuralMapError(f"could not reserve a free version folder under {root}.")


def publish_dir(staging: Path, root: str | os.PathLike[str]) -> Path:
    """Renames a complete staging folder to the next free ``root/version_<N>``."""
    target = next_version_dir(root)
    os.replace(staging, target)  # replaces the empty reserved folder atomically
    return target


_STAGING_PREFIX = ".tmp-version_"


def check_experiment_name(name: str, *, option: str = "--experiment") -> str:
    """The one rule for experiment names (trainers and studies): a plain, visible folder
    name inside the runs folder.

    Args:
        name: The experiment name.
        option: The option to name in the message.

    Returns:
        ``name``.

    Raises:
        NeuralMapError: Empty, ``.``/``..``, a path separator, or a leading ``.`` (hidden
            folders are the staging folders of runs in progress).
    """
    text = str(name)
    if (not text or text.startswith(".") or "/" in text or "\\" in text or os.sep in text
            or Path(text).name != text):
        raise NeuralMapError(
            f"{option} {text!r} must be a plain folder name inside --runs_dir (no '/', "
            "'\\', no leading '.', not '..'); choose the parent folder with --runs_dir "
            "instead."
        )
    return text


def _pid_alive(pid: int) -> bool:
    """Whether a process with this id runs on this machine (signal 0 probes, sends nothing)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # exists but belongs to someone else, or cannot tell: keep its folder
    return True


def remove_stale_staging(root: str | os.PathLike[str]) -> list[Path]:
    """Removes the staging folders in ``root`` left by processes that no longer run
    (a study killed with SIGKILL cannot clean up after itself).

    Staging folders are named ``.tmp-version_<pid>_<random>``; folders of a live process,
    or without a pid in the name, are kept.

    Returns:
        The removed folders.
    """
    removed = []
    for path in Path(root).glob(f"{_STAGING_PREFIX}*"):
        pid_text = path.name[len(_STAGING_PREFIX):].split("_", 1)[0]
        if path.is_dir() and pid_text.isdigit() and not _pid_alive(int(pid_text)):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def make_staging_dir(root: str | os.PathLike[str]) -> Path:
    """A new hidden staging folder ``root/.tmp-version_<pid>_<random>`` (``root`` created),
    after removing the stale ones of dead processes (`remove_stale_staging`)."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(root)
    path = Path(tempfile.mkdtemp(prefix=f"{_STAGING_PREFIX}{os.getpid()}_", dir=root))
    os.chmod(path, default_mode(directory=True))
    return path


@contextmanager
def staging_dir(root: str | os.PathLike[str]) -> Iterator[Path]:
    """A hidden temporary folder in ``root``, removed again unless it was published.

    Used as ``with staging_dir(root) as tmp: ...write...; out = publish_dir(tmp, root)``:
    an exception or Ctrl-C inside the block leaves no ``.tmp-version_*`` folder behind,
    and a folder left by a killed process is removed by the next run into ``root``.
    """
    path = make_staging_dir(root)
    try:
        yield path
    finally:
        if path.exists():
            shutil.rmtree(path, ignore_errors=True)


@contextmanager
def replacing_dir(target: str | os.PathLike[str], *, option: str = "--out") -> Iterator[Path]:
    """Builds a folder under a hidden name beside ``target``; puts it in place when whole.

    ``with replacing_dir(out) as tmp: ...write into tmp...``: when the block ends without an
    exception the hidden ``.<name>.tmp-*`` folder replaces ``target`` (an earlier complete
    output is moved aside and deleted only then); an exception, Ctrl-C or ``kill -9``
    leaves ``target`` as it was. Only one builder per target at a time: an exclusive lock
    on ``.<name>.lock`` (released by the kernel when its process dies) refuses a second;
    hidden builds left by killed runs are removed when the lock is taken.

    The replacement is two renames (old aside, new in); a crash between them, a window of
    microseconds, leaves the complete old output under ``.<name>.old-*``.

    Raises:
        NeuralMapError: ``target`` is a file, its parent is not writable, or another run
            is building it now.
    """
    import fcntl

    target = Path(target)
    if target.exists() and not target.is_dir():
        raise NeuralMapError(
            f"{option} '{target}' is a file; give a folder (new or an earlier output).")
    parent = target.parent
    lock_path = parent / f".{target.name}.lock"
    try:
        parent.mkdir(parents=True, exist_ok=True)
        lock = open(lock_path, "a+b")  # noqa: SIM115 - held to the end
    except OSError as exc:
        raise NeuralMapError(f"{option} '{target}': cannot write in '{parent}' ({exc}).") from None
    try:
        try:
            fcntl.flock(lock.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            lock.close()
            raise NeuralMapError(
                f"{option} '{target}': another run is writing this output now; wait for it "
                f"to finish or give another {option}.") from None
        for stale in (*parent.glob(f".{target.name}.tmp-*"), *parent.glob(f".{target.name}.old-*")):
            shutil.rmtree(stale, ignore_errors=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=parent))
        os.chmod(staging, default_mode(directory=True))
        try:
            yield staging
            old = None
            if target.exists():
                old = parent / f".{target.name}.old-{os.getpid()}"
                os.replace(target, old)
            os.replace(staging, target)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        finally:
            if staging.exists():
                shutil.rmtree(staging, ignore_errors=True)
            lock_path.unlink(missing_ok=True)  # still held: no other run can be past flock
    finally:
        lock.close()


class _NumberLoader(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2 floats: ``1e20`` and ``1.0e20`` are numbers.

    PyYAML follows YAML 1.1, where an exponent needs a sign and a dot (``1.0e+20``), so
    ``1e20`` or ``9e0`` silently become strings; every config of the toolkit means numbers.
    """


_NumberLoader.yaml_implicit_resolvers = {
    key: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:float"]
    for key, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.copy().items()
}
_NumberLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(
        r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
        |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def load_yaml(text: str) -> Any:
    """Parses YAML text like ``yaml.safe_load``, reading ``1e20``/``1.0e20`` as floats."""
    return yaml.load(text, Loader=_NumberLoader)  # noqa: S506 - a SafeLoader subclass
