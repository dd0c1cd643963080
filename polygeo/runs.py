"""What every long job needs: atomic writes, safe checkpoints, resume, a JSONL log, progress.

* :func:`atomic_write` (and ``_bytes`` / ``_text`` / ``_json``): the file is written under a
  temporary name in the destination's folder, flushed and fsynced, then ``os.replace``-d onto
  the final name. A reader sees the old file or the new one, never half of either; if the
  write fails the old file is left as it was and the temporary file is removed.
* :func:`save_checkpoint` / :func:`load_checkpoint`: a checkpoint is a ``torch.save`` file
  holding only plain data: a tree (dicts, lists, tuples) of tensors and Python scalars, and
  the metadata as a JSON *string*. It is read with ``torch.load(weights_only=True)``, whose
  unpickler rebuilds tensors and plain containers only and refuses every other global, so
  that loading a checkpoint received from someone else never runs code. (``safetensors``
  would be as safe but is not a dependency and holds flat tensor maps only; ``torch.save``
  keeps optimizer and scheduler states, with their integer keys and tuples, as they are.)
  NumPy arrays are stored as tensors and come back as NumPy arrays.
* :func:`fingerprint`: a stable hash of settings (a dataclass or a mapping), the key of
  :func:`resume_state`, which continues a run only with the settings it was started with.
* :class:`JsonlLog`: one JSON record per line, flushed at each record; its reader ignores a
  torn last line (a process killed in the middle of a write).
* :func:`progress`: a tqdm bar that can be quieted.
* :func:`record_path`: how a record (a benchmark's JSON, a shipped model's) names a file
  without the machine's paths.

torch is imported by the checkpoint functions only, so that the file helpers stay light.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import io
import json
import math
import os
import pickle
import secrets
import sys
import zipfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import IO, Any, NamedTuple

import numpy as np

__all__ = [
    "CheckpointError",
    "SettingsChangedError",
    "Checkpoint",
    "CHECKPOINT_FORMAT",
    "CHECKPOINT_VERSION",
    "CHECKPOINT_NAME",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_write_json",
    "save_checkpoint",
    "load_checkpoint",
    "fingerprint",
    "canonical_json",
    "resume_state",
    "JsonlLog",
    "read_jsonl",
    "truncate_jsonl",
    "progress",
    "record_path",
    "record_command",
]

#: Value of the ``format`` field of a checkpoint's header.
CHECKPOINT_FORMAT = "polygeo.runs.checkpoint"
#: Version of the checkpoint layout written by :func:`save_checkpoint` (and the only one read).
CHECKPOINT_VERSION = 1
#: File name of the checkpoint inside a run folder (:func:`resume_state`).
CHECKPOINT_NAME = "checkpoint.pt"


class CheckpointError(ValueError):
    """A file that is not a checkpoint this version of polygeo reads safely."""


class SettingsChangedError(CheckpointError):
    """The checkpoint of a run folder was written with other settings."""


class Checkpoint(NamedTuple):
    """What :func:`load_checkpoint` returns (unpacks as ``tensors, meta``).

    Attributes
    ----------
    tensors : dict
        The tree given to :func:`save_checkpoint` (tensors on the CPU, NumPy arrays back as
        NumPy arrays).
    meta : dict
        The JSON metadata.
    """

    tensors: dict
    meta: dict


# --------------------------------------------------------------------------------------------
# Atomic writes
# --------------------------------------------------------------------------------------------


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # not possible on every platform (Windows): the replace is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def record_path(path: str | os.PathLike, root: str | os.PathLike | None = None) -> str:
    """How a record names a file, without the machine's file system.

    An absolute path under ``root`` (a repository) becomes relative to it
    (``draping/data/gaps_tshirt.pt``), one under the home directory ``~/...``, any other
    absolute path ``.../<folder>/<name>`` (which run it was, not where it lay). A relative
    path, or a word that is not a path, is returned as it is.

    Parameters
    ----------
    path : str or path-like
        The file (or any command-line word).
    root : str or path-like, optional
        The folder whose files are named relative to it.

    Returns
    -------
    str
    """
    p = os.fspath(path)
    if not os.path.isabs(p):
        return p
    p = os.path.normpath(p)
    for base, prefix in ((root, ""), (Path.home(), "~/")):
        if base is None:
            continue
        base = os.path.normpath(os.path.abspath(os.fspath(base)))
        if p.startswith(base + os.sep):
            return prefix + p[len(base) + 1:]
    parts = Path(p).parts[1:]
    return ".../" + "/".join(parts[-2:]) if len(parts) > 1 else p


def record_command(words: Iterable[str], root: str | os.PathLike | None = None) -> str:
    """A command line for a record: its words joined, every path in them by :func:`record_path`.

    Paths inside ``--option=value`` words and comma-separated lists are mapped part by part.

    Parameters
    ----------
    words : iterable of str
        The command's words (e.g. ``["polygeo", *sys.argv[1:]]``).
    root : str or path-like, optional
        The folder whose files are named relative to it.

    Returns
    -------
    str
    """

    def one(word: str) -> str:
        head, eq, value = word.partition("=") if word.startswith("-") else ("", "", word)
        return head + eq + ",".join(record_path(p, root) if p else p for p in value.split(","))

    return " ".join(one(os.fspath(w)) for w in words)


def atomic_write(path: str | os.PathLike, write_fn: Callable[[IO[bytes]], Any]) -> Path:
    """Write a file through ``write_fn`` so that it appears complete or not at all.

    ``write_fn`` receives a binary file object opened on a new temporary file in the
    destination's folder (same file system, so the final ``os.replace`` is atomic). After it
    returns, the file is flushed, fsynced and renamed onto ``path``. If ``write_fn`` raises,
    the temporary file is removed, ``path`` is left as it was (old content or absent) and the
    exception propagates. The new file gets the usual permissions (``0o666`` less the umask).

    Parameters
    ----------
    path : str or os.PathLike
        Destination; its folder is created if missing.
    write_fn : callable
        ``write_fn(fh)`` writes the content to the binary file object ``fh``.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    dest = Path(os.fspath(path))
    dest.parent.mkdir(parents=True, exist_ok=True)
    while True:
        tmp = dest.parent / f".{dest.name}.{secrets.token_hex(6)}.tmp"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0),
                         0o666)
            break
        except FileExistsError:  # pragma: no cover - 48 random bits collided
            continue
    try:
        with os.fdopen(fd, "wb") as fh:
            write_fn(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, dest)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    _fsync_dir(dest.parent)
    return dest


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` atomically (:func:`atomic_write`); returns the path."""
    return atomic_write(path, lambda fh: fh.write(data))


def atomic_write_text(path: str | os.PathLike, text: str, *, encoding: str = "utf-8") -> Path:
    """Write ``text`` atomically in ``encoding`` (:func:`atomic_write`); returns the path."""
    return atomic_write_bytes(path, text.encode(encoding))


def atomic_write_json(path: str | os.PathLike, obj: Any, *, indent: int | None = 1) -> Path:
    """Write ``obj`` as JSON atomically (:func:`atomic_write`), with a final newline.

    Raises
    ------
    TypeError
        If ``obj`` is not JSON-able (nothing is written then).
    """
    text = json.dumps(obj, indent=indent) + "\n"
    return atomic_write_text(path, text)


# --------------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------------

_SCALARS = (bool, int, float, str, type(None))


def _pack(x: Any, path: list, numpy_paths: list, in_tuple: bool = False) -> Any:
    """Copy of the tree with NumPy arrays as tensors and NumPy scalars as Python scalars."""
    import torch

    where = "tensors" + "".join(f"[{k!r}]" for k in path)
    if isinstance(x, torch.Tensor):
        return x.detach().cpu()
    if isinstance(x, np.ndarray):
        if x.dtype == object:
            raise TypeError(f"{where}: expected a numeric array, got an object array")
        if in_tuple:
            raise TypeError(f"{where}: NumPy arrays inside tuples are not supported (use a list)")
        numpy_paths.append(list(path))
        return torch.from_numpy(np.ascontiguousarray(x))
    if isinstance(x, np.generic):
        return x.item()
    # subclasses (IntEnum, ...) become the plain type: they would be pickled by class
    for plain in (type(None), bool, int, float, str):
        if isinstance(x, plain):
            return x if plain is type(None) else plain(x)
    if isinstance(x, Mapping):
        out = {}
        for k, v in x.items():
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise TypeError(f"{where}: expected str or int keys, got {type(k).__name__}")
            key = str(k) if isinstance(k, str) else int(k)
            out[key] = _pack(v, [*path, key], numpy_paths)
        return out
    if isinstance(x, (list, tuple)):
        tup = isinstance(x, tuple)
        items = [_pack(v, [*path, i], numpy_paths, tup) for i, v in enumerate(x)]
        return tuple(items) if tup else items
    raise TypeError(
        f"{where}: expected tensors, arrays, Python scalars and dicts/lists/tuples of them, "
        f"got {type(x).__name__}"
    )


def save_checkpoint(
    path: str | os.PathLike,
    tensors: Mapping[str, Any],
    meta: Mapping[str, Any] | None = None,
) -> Path:
    """Write a checkpoint atomically: plain tensors and JSON metadata, no pickled objects.

    Parameters
    ----------
    path : str or os.PathLike
        Destination (``.pt``); written by :func:`atomic_write`.
    tensors : mapping
        ``str -> tensor | ndarray | nested mapping``; lists, tuples and Python scalars may
        appear inside (a ``torch.optim`` state dict is stored as it is). Tensors are moved to
        the CPU and detached.
    meta : mapping, optional
        JSON-able metadata (settings, step, history, the run's :func:`fingerprint`).

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    TypeError
        If ``tensors`` holds another kind of object (a class instance, a function) or
        ``meta`` is not JSON-able; nothing is written then.
    """
    if not isinstance(tensors, Mapping):
        raise TypeError(f"tensors: expected a mapping, got {type(tensors).__name__}")
    numpy_paths: list = []
    tree = _pack(tensors, [], numpy_paths)
    try:
        meta_json = json.dumps(dict(meta or {}))
    except (TypeError, ValueError) as exc:
        raise TypeError(f"meta: expected JSON-able metadata ({exc})") from exc
    import torch

    header = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "numpy": numpy_paths}
    blob = {"header": json.dumps(header), "meta": meta_json, "tensors": tree}
    return atomic_write(path, lambda fh: torch.save(blob, fh))


def _check_plain(x: Any, where: str) -> None:
    import torch

    if isinstance(x, torch.Tensor) or isinstance(x, _SCALARS):
        return
    if isinstance(x, dict):
        for k, v in x.items():
            _check_plain(v, f"{where}[{k!r}]")
        return
    if isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            _check_plain(v, f"{where}[{i}]")
        return
    raise CheckpointError(f"{where}: unexpected {type(x).__name__} in a checkpoint")


def _unpack_numpy(tree: dict, numpy_paths: list) -> dict:
    try:
        for p in numpy_paths:
            node = tree
            for k in p[:-1]:
                node = node[k]
            node[p[-1]] = node[p[-1]].numpy()
    except (KeyError, IndexError, TypeError, AttributeError) as exc:
        raise CheckpointError(f"checkpoint: damaged header (NumPy entry {p!r})") from exc
    return tree


def load_checkpoint(path: str | os.PathLike) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint`, without executing any code.

    The file is read with ``torch.load(weights_only=True, map_location="cpu")``: tensors and
    plain containers only; a pickled class instance, function or any other global is refused
    before it is built.

    Parameters
    ----------
    path : str or os.PathLike
        The checkpoint.

    Returns
    -------
    Checkpoint
        ``(tensors, meta)``.

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    CheckpointError
        (a ``ValueError``) if the file carries pickled objects other than tensors and plain
        containers, is truncated or not a checkpoint, is a checkpoint of another format
        version, or was written by an older polygeo (a bare ``torch.save`` of a dict).
    """
    import torch

    p = Path(os.fspath(path))
    if not p.is_file():
        raise FileNotFoundError(f"path: no checkpoint at {str(p)!r}")
    try:
        blob = torch.load(p, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(
            f"{str(p)!r} carries pickled objects other than tensors and plain containers; "
            "it is refused because loading it could run arbitrary code"
        ) from exc
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile, ValueError) as exc:
        raise CheckpointError(
            f"{str(p)!r} is truncated or not a checkpoint ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0] if str(exc) else ''})"
        ) from exc
    if not (isinstance(blob, dict) and isinstance(blob.get("header"), str)):
        raise CheckpointError(
            f"{str(p)!r} is not a {CHECKPOINT_FORMAT} file (written by an older polygeo, "
            "whose checkpoints are not read: start the run afresh in a new folder)"
        )
    try:
        header = json.loads(blob["header"])
        meta = json.loads(blob.get("meta", "{}"))
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{str(p)!r}: damaged header ({exc})") from exc
    if not isinstance(header, dict) or header.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{str(p)!r} is not a {CHECKPOINT_FORMAT} file")
    if header.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"{str(p)!r} has checkpoint format version {header.get('version')!r}; this polygeo "
            f"reads version {CHECKPOINT_VERSION} only"
        )
    tree = blob.get("tensors")
    if not isinstance(tree, dict) or not isinstance(meta, dict):
        raise CheckpointError(f"{str(p)!r}: expected a dict of tensors and a dict of metadata")
    _check_plain(tree, "tensors")
    return Checkpoint(_unpack_numpy(tree, header.get("numpy", [])), meta)


# --------------------------------------------------------------------------------------------
# Fingerprints and resume
# --------------------------------------------------------------------------------------------


def _plain(x: Any, where: str) -> Any:
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: _plain(getattr(x, f.name), f"{where}.{f.name}")
                for f in dataclasses.fields(x)}
    if isinstance(x, enum.Enum):
        return _plain(x.value, where)
    if isinstance(x, np.generic):
        return _plain(x.item(), where)
    if isinstance(x, bool) or x is None or isinstance(x, (int, str)):
        return x
    if isinstance(x, float):
        if math.isnan(x) or math.isinf(x):
            return {"$float": repr(x)}  # JSON has no NaN/inf; repr is stable
        return x
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    if isinstance(x, Mapping):
        out = {}
        for k, v in x.items():
            if not isinstance(k, str):
                raise TypeError(f"{where}: expected str keys, got {type(k).__name__}")
            out[k] = _plain(v, f"{where}[{k!r}]")
        return out
    if isinstance(x, (list, tuple)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(x)]
    raise TypeError(
        f"{where}: expected a dataclass, mapping, sequence or scalar, got {type(x).__name__}"
    )


def canonical_json(settings: Any) -> str:
    """Canonical JSON of settings: sorted keys, no spaces, floats by ``repr``.

    Dataclasses become the mapping of their fields (nested dataclasses too), tuples become
    lists, enums their value, paths strings, NumPy scalars Python scalars.

    Raises
    ------
    TypeError
        On a value of another kind (a tensor, a function, an object).
    """
    return json.dumps(_plain(settings, "settings"), sort_keys=True, separators=(",", ":"),
                      ensure_ascii=True, allow_nan=False)


def fingerprint(settings: Any) -> str:
    """Stable hash of settings (a dataclass or a mapping), the key of a resumable run.

    The SHA-256 of :func:`canonical_json`, shortened to 16 hex digits. It is the same in
    every process and on every platform (no ``hash()``, whose salt changes per process;
    floats are written by their shortest round-trip ``repr``) and changes when any field
    changes. ``1`` and ``1.0`` are different values. A dataclass hashes as the mapping of its
    fields (the class name is not part of the key, so that moving or renaming a settings
    class does not orphan runs; adding a field changes the fingerprint).

    Parameters
    ----------
    settings : dataclass instance, mapping, or JSON-able value

    Returns
    -------
    str
        16 lowercase hex digits.

    Raises
    ------
    TypeError
        On a value that has no canonical JSON form (:func:`canonical_json`).
    """
    return hashlib.sha256(canonical_json(settings).encode("ascii")).hexdigest()[:16]


def resume_state(
    run_dir: str | os.PathLike, fingerprint: str, *, name: str = CHECKPOINT_NAME
) -> Checkpoint | None:
    """The checkpoint of a run folder if it was written with the same settings.

    The checkpoint must carry the fingerprint of its settings as ``meta["fingerprint"]``
    (:func:`save_checkpoint` with ``meta={"fingerprint": fingerprint(settings), ...}``).

    Parameters
    ----------
    run_dir : str or os.PathLike
        The run's folder.
    fingerprint : str
        :func:`fingerprint` of the current settings.
    name : str
        File name of the checkpoint in the folder.

    Returns
    -------
    Checkpoint or None
        None when the folder holds no checkpoint (a fresh run).

    Raises
    ------
    SettingsChangedError
        (a :class:`CheckpointError`) if the checkpoint was written with other settings.
    CheckpointError
        If the checkpoint cannot be read safely (:func:`load_checkpoint`).
    """
    p = Path(os.fspath(run_dir)) / name
    if not p.is_file():
        return None
    ck = load_checkpoint(p)
    found = ck.meta.get("fingerprint")
    if found != fingerprint:
        raise SettingsChangedError(
            f"{str(p)!r} was written with other settings (fingerprint {found!r}, the current "
            f"settings give {fingerprint!r}): the settings changed since the run started; "
            "resume with the same settings, or use another folder / start afresh"
        )
    return ck


# --------------------------------------------------------------------------------------------
# JSONL log
# --------------------------------------------------------------------------------------------


def read_jsonl(path: str | os.PathLike) -> list[Any]:
    """Records of a JSONL file, ignoring a torn last line.

    Parameters
    ----------
    path : str or os.PathLike
        The file (absent: no records).

    Returns
    -------
    list
        One decoded JSON value per complete line (blank lines skipped).

    Raises
    ------
    ValueError
        If a line other than an unterminated last one is not JSON (naming the line).
    """
    p = Path(os.fspath(path))
    if not p.is_file():
        return []
    data = p.read_bytes()
    lines = data.split(b"\n")
    torn = lines.pop()  # text after the last newline: b"" for a complete file
    out = []
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{str(p)!r} line {i}: not JSON ({exc})") from exc
    if torn.strip():
        try:  # a last record without its newline is kept if it is complete
            out.append(json.loads(torn))
        except json.JSONDecodeError:
            pass
    return out


def truncate_jsonl(path: str | os.PathLike, keep: Callable[[Any], bool]) -> int:
    """Drop the records of a JSONL file that ``keep`` rejects; return how many were dropped.

    What a run resumed from a checkpoint does with its logs: the lines written after the
    checkpoint (by a process stopped before the next one) are dropped, so that the steps
    done again are not logged twice. A torn last line is dropped too. The file is rewritten
    atomically (:func:`atomic_write_text`) and only when something is dropped.

    Parameters
    ----------
    path : str or os.PathLike
        The file (absent: nothing to do, 0).
    keep : callable
        ``keep(record) -> bool`` for each decoded record, in file order.

    Returns
    -------
    int
        The number of records dropped.

    Raises
    ------
    TypeError
        If ``keep`` is not callable.
    ValueError
        If a line other than an unterminated last one is not JSON (:func:`read_jsonl`).

    Examples
    --------
    >>> truncate_jsonl(run / "log.jsonl", lambda r: r["step"] < ck.meta["step"])  # doctest: +SKIP
    """
    if not callable(keep):
        raise TypeError(f"keep must be callable (a record -> bool), got {type(keep).__name__}")
    p = Path(os.fspath(path))
    if not p.is_file():
        return 0
    data = p.read_bytes()
    records = read_jsonl(p)
    kept = [r for r in records if keep(r)]
    torn = bool(data) and not data.endswith(b"\n")
    if len(kept) < len(records) or torn:
        atomic_write_text(p, "".join(json.dumps(r, separators=(",", ":")) + "\n" for r in kept))
    return len(records) - len(kept)


class JsonlLog:
    """Append-only log of JSON records, one per line, flushed after each.

    Opening a log whose last line is torn (a process killed while writing) cuts that line
    off, so that the next record starts on a line of its own.

    Parameters
    ----------
    path : str or os.PathLike
        The file (created with its folder if missing; appended to otherwise).
    fsync : bool
        Also ``os.fsync`` after each record (survives a power cut; slower).

    Examples
    --------
    >>> with JsonlLog(run / "log.jsonl") as log:  # doctest: +SKIP
    ...     log.append({"step": 1, "loss": 0.5})
    """

    def __init__(self, path: str | os.PathLike, *, fsync: bool = False):
        self.path = Path(os.fspath(path))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fsync = bool(fsync)
        self._fh: io.BufferedWriter | None = open(self.path, "ab")  # noqa: SIM115
        self._cut_torn_tail()

    def _cut_torn_tail(self) -> None:
        with open(self.path, "rb") as fh:
            data = fh.read()
        if data and not data.endswith(b"\n"):
            keep = data.rfind(b"\n") + 1
            self._fh.truncate(keep)
            self._fh.seek(0, os.SEEK_END)

    def append(self, record: Any) -> None:
        """Write one JSON-able record as a line and flush it.

        Raises
        ------
        TypeError
            If ``record`` is not JSON-able (nothing is written).
        ValueError
            If the log is closed.
        """
        if self._fh is None:
            raise ValueError(f"{str(self.path)!r}: the log is closed")
        line = (json.dumps(record, separators=(",", ":")) + "\n").encode("utf-8")
        self._fh.write(line)
        self._fh.flush()
        if self._fsync:
            os.fsync(self._fh.fileno())

    def read(self) -> list[Any]:
        """All records written so far (:func:`read_jsonl`)."""
        return read_jsonl(self.path)

    def close(self) -> None:
        """Close the file (appending afterwards raises)."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def __enter__(self) -> JsonlLog:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# --------------------------------------------------------------------------------------------
# Progress
# --------------------------------------------------------------------------------------------


def progress(
    iterable: Iterable | None = None,
    total: int | None = None,
    desc: str | None = None,
    quiet: bool | None = False,
    **kwargs: Any,
):
    """A tqdm progress bar over ``iterable`` that can be quieted.

    Parameters
    ----------
    iterable : iterable, optional
        What to iterate (None: a manual bar updated with ``.update(n)``).
    total : int, optional
        Number of items (default ``len(iterable)`` when it has one).
    desc : str, optional
        Label in front of the bar.
    quiet : bool or None
        True: no bar. False (default): a bar on stderr. None: a bar only when stderr is a
        terminal (tqdm's own rule), so that logs and CI output are not filled with carriage
        returns.
    **kwargs
        Passed to ``tqdm`` (``initial``, ``leave``, ``unit``, ...).

    Returns
    -------
    tqdm.tqdm
        Iterate it; ``set_postfix`` and ``close`` work (and do nothing) when quiet.
    """
    from tqdm.auto import tqdm

    disable = True if quiet else (None if quiet is None else False)
    return tqdm(iterable, total=total, desc=desc, disable=disable, file=sys.stderr, **kwargs)
