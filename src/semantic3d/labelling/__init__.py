"""The browser labelling tool and viewer: level of detail, geometry, journal, session, app.

- :mod:`~semantic3d.labelling.lod`: the level-of-detail octree of a cache, built once.
- :mod:`~semantic3d.labelling.geometry`: polygon splits through a camera, RANSAC fits.
- :mod:`~semantic3d.labelling.journal`: the append-only SQLite journal (undo, redo, resume).
- :mod:`~semantic3d.labelling.session`: class layers, the working set, operations, save.
- :mod:`~semantic3d.labelling.selections` / :mod:`~semantic3d.labelling.fits`: the 2D
  (polygon, lasso, brush) and 3D (model fits with a region and a preview) workflows.
- :mod:`~semantic3d.labelling.delta`: an operation's change as packed bit masks.
- :mod:`~semantic3d.labelling.progress`: progress and cancel of the running operation.
- :mod:`~semantic3d.labelling.stats`: counts and confusion of the working set or the view.
- :mod:`~semantic3d.labelling.saving`: where a session may write; saves in step with the journal.
- :mod:`~semantic3d.labelling.opening`: caches, which labels are read, where saves go.
- :mod:`~semantic3d.labelling.cachedir`: the per-user cache folder (never beside the data).
- :mod:`~semantic3d.labelling.security`: loopback Host, per-launch secret, same-origin writes.
- :mod:`~semantic3d.labelling.app`: ``create_label_app(session, port=...)``, the app and page.

Names are loaded on first use; the app needs the ``label`` extra (FastAPI, uvicorn).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.labelling.app import create_label_app
    from semantic3d.labelling.errors import (
        JournalError,
        LabelFileError,
        OperationError,
        ReadOnlyError,
    )
    from semantic3d.labelling.geometry import fit_model, select_in_polygon
    from semantic3d.labelling.journal import Journal
    from semantic3d.labelling.labelfile import read_label_file
    from semantic3d.labelling.lod import LodIndex, build_lod, open_lod
    from semantic3d.labelling.opening import open_label_session, plan_labels
    from semantic3d.labelling.session import LabelSession

__all__ = [
    "Journal",
    "JournalError",
    "LabelFileError",
    "LabelSession",
    "LodIndex",
    "OperationError",
    "ReadOnlyError",
    "build_lod",
    "create_label_app",
    "fit_model",
    "open_label_session",
    "open_lod",
    "plan_labels",
    "read_label_file",
    "select_in_polygon",
]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "create_label_app": "semantic3d.labelling.app",
        "JournalError": "semantic3d.labelling.errors",
        "LabelFileError": "semantic3d.labelling.errors",
        "OperationError": "semantic3d.labelling.errors",
        "ReadOnlyError": "semantic3d.labelling.errors",
        "fit_model": "semantic3d.labelling.geometry",
        "select_in_polygon": "semantic3d.labelling.geometry",
        "Journal": "semantic3d.labelling.journal",
        "read_label_file": "semantic3d.labelling.labelfile",
        "LodIndex": "semantic3d.labelling.lod",
        "build_lod": "semantic3d.labelling.lod",
        "open_lod": "semantic3d.labelling.lod",
        "LabelSession": "semantic3d.labelling.session",
        "open_label_session": "semantic3d.labelling.opening",
        "plan_labels": "semantic3d.labelling.opening",
    },
)
