"""Model files: a JSON header line that is checked before any payload is loaded.

Every baseline's model file starts with ``MAGIC`` and one JSON line (format and version,
package and library versions, resolved configuration, training scans, seed), then the
payload (a pickle for scikit-learn models, a state dict for torch ones). Readers check
the header first, so a file of another kind or version fails with a clear message instead
of an unpickling error or silently different results. Payloads can be pickles: load only
model files you trust. Writers stage the file and rename it into place.
"""

from __future__ import annotations

import json
import uuid
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import IO, Any

from semantic3d.core.errors import Semantic3DError

__all__ = ["ModelFileError", "check_versions", "read_header", "write_model_file"]

_MAX_HEADER_BYTES = 1 << 20


class ModelFileError(Semantic3DError, ValueError):
    """A file is not a model of the expected kind, or was written by an incompatible version."""


def write_model_file(
    path: str | Path,
    *,
    magic: bytes,
    header: Mapping[str, Any],
    write_payload: Callable[[IO[bytes]], None],
) -> Path:
    """Write ``magic``, the JSON ``header`` line and the payload to ``path``, atomically.

    Parent folders are created; an error or Ctrl-C leaves what was at ``path`` as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.partial")
    try:
        with temp.open("wb") as stream:
            stream.write(magic + json.dumps(dict(header)).encode() + b"\n")
            write_payload(stream)
        temp.replace(path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise
    return path


def read_header(
    stream: IO[bytes], path: Path, *, magic: bytes, kind: str, file_format: str, version: int
) -> dict[str, Any]:
    """The header of an open model file, checked; ``stream`` is left at the payload.

    Raises:
        ModelFileError: other magic bytes, a corrupt header, another format or version.
    """
    line = stream.readline(_MAX_HEADER_BYTES)
    if not line.startswith(magic):
        raise ModelFileError(f"{path}: not a semantic3d {kind} (bad magic bytes)")
    try:
        header: dict[str, Any] = json.loads(line[len(magic) :])
    except ValueError as exc:
        raise ModelFileError(f"{path}: corrupt model header: {exc}") from exc
    if header.get("format") != file_format or header.get("format_version") != version:
        raise ModelFileError(
            f"{path}: expected format {file_format} v{version}, found "
            f"{header.get('format')} v{header.get('format_version')}"
        )
    return header


def check_versions(
    header: Mapping[str, Any],
    path: Path,
    *,
    expected: Mapping[str, tuple[str, str]],
    retrain: str,
) -> None:
    """Refuse a model whose recorded versions differ from this process's.

    Args:
        header: the file's header.
        path: the file (for the message).
        expected: header key -> (library name, version this process has), e.g.
            ``{"package_version": ("semantic3d", "0.1.0")}``.
        retrain: the command that makes a new model, named in the message.
    """
    found = {key: header.get(key) for key in expected}
    if any(found[key] != version for key, (_, version) in expected.items()):
        written = " with ".join(f"{name} {found[key]}" for key, (name, _) in expected.items())
        this = " with ".join(f"{name} {version}" for name, version in expected.values())
        raise ModelFileError(
            f"{path}: model written by {written}; this is {this}: retrain it ({retrain})"
        )
