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
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, TypeVar

from semantic3d.core.errors import Semantic3DError, installed_version, require

__all__ = [
    "ModelFileError",
    "ModelFileFormat",
    "check_versions",
    "read_header",
    "write_model_file",
]

_Model = TypeVar("_Model")

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


@dataclass(frozen=True, slots=True)
class ModelFileFormat:
    """One baseline's kind of model file: its magic bytes, name and format version.

    Each baseline's ``persistence`` module holds one of these and calls it to write its
    files, read their headers and open them for loading; the checks and messages are the
    same for every baseline.
    """

    magic: bytes
    kind: str
    """What the file holds, for messages ("covariance model")."""
    name: str
    """The header's ``format`` value."""
    version: int
    """The header's ``format_version``; files of another version are refused."""

    def write(
        self,
        path: str | Path,
        header: Mapping[str, Any],
        write_payload: Callable[[IO[bytes]], None],
    ) -> Path:
        """Write the header (format and version first) and payload atomically."""
        full = {"format": self.name, "format_version": self.version, **header}
        return write_model_file(path, magic=self.magic, header=full, write_payload=write_payload)

    def read_header(self, path: str | Path) -> dict[str, Any]:
        """The checked JSON header of the file at ``path``, without loading the payload."""
        with self.open(path) as (header, _):
            return header

    @contextmanager
    def open(self, path: str | Path) -> Iterator[tuple[dict[str, Any], IO[bytes]]]:
        """``(header, stream)``: the checked header, and the stream at the payload.

        Raises:
            ModelFileError: unreadable, another kind of file, another format or version.
        """
        path = Path(path)
        try:
            with path.open("rb") as stream:
                header = read_header(
                    stream,
                    path,
                    magic=self.magic,
                    kind=self.kind,
                    file_format=self.name,
                    version=self.version,
                )
                yield header, stream
        except OSError as exc:
            raise ModelFileError(f"{path}: cannot read the model: {exc.strerror}") from exc

    def load_joblib(
        self, path: str | Path, *, payload_type: type[_Model], extra: str, retrain: str
    ) -> _Model:
        """Load a scikit-learn model written with a joblib payload.

        The header must record this semantic3d's and this scikit-learn's versions (trees
        pickled by another version are refused rather than trusted).
        """
        from semantic3d import __version__

        joblib: Any = require("joblib", extra)
        # from the metadata: importing scikit-learn takes ~0.9 s, and a payload without
        # its objects (the covariance model's compiled trees) never needs it
        sklearn_version = installed_version("scikit-learn", extra)
        with self.open(path) as (header, stream):
            check_versions(
                header,
                Path(path),
                expected={
                    "package_version": ("semantic3d", __version__),
                    "sklearn_version": ("scikit-learn", sklearn_version),
                },
                retrain=retrain,
            )
            model = joblib.load(stream)
        if not isinstance(model, payload_type):
            raise ModelFileError(
                f"{path}: expected a {payload_type.__name__} payload, found {type(model).__name__}"
            )
        return model
