"""Errors of the labelling app (all :class:`~semantic3d.core.errors.Semantic3DError`)."""

from __future__ import annotations

from semantic3d.core.errors import DataFormatError, Semantic3DError


class LabelFileError(DataFormatError):
    """A ``.labels`` file does not fit the scan: wrong length or values outside 0..8."""


class JournalError(DataFormatError):
    """A journal file is unreadable or belongs to another scan."""


class OperationError(Semantic3DError, ValueError):
    """A labelling operation cannot run (bad parameters, nothing to undo, a locked layer)."""


class ReadOnlyError(Semantic3DError, PermissionError):
    """A change was asked of a read-only viewer session."""


class WholeScanError(OperationError):
    """An assignment would change the whole scan and was not confirmed."""


class OperationCancelledError(OperationError):
    """The user cancelled a running operation before it changed anything."""
