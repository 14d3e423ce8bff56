"""Method cards: checked once, stored on the submission row, read back as :class:`MethodInfo`.

The one place that maps a :class:`~semantic3d.evaluation.MethodInfo` to a submission's
columns (:func:`method_columns`) and back (:func:`method_of`); a card sent to the API
becomes a ``MethodInfo`` through :meth:`semantic3d.server.schemas.MethodCardIn.to_method`.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

from semantic3d.evaluation import MethodInfo
from semantic3d.server.errors import InvalidInputError
from semantic3d.server.models import Submission

# MethodInfo fields stored under the same name on the row; ``name`` is ``method_name``.
_SAME_NAME = ("description", "paper_url", "code_url", "runtime_s", "hardware")


def validate_method(method: MethodInfo) -> MethodInfo:
    """Check a method card's fields (links must be http(s): they are shown as links); the
    card with its text stripped."""
    problems = []
    if not method.name.strip() or len(method.name) > 200:
        problems.append(f"method name: expected 1-200 characters, found {len(method.name)}")
    for field, value in (("paper_url", method.paper_url), ("code_url", method.code_url)):
        if value and (not value.startswith(("http://", "https://")) or len(value) > 500):
            problems.append(f"{field}: expected an http(s) address, found {value[:60]!r}")
    if method.runtime_s is not None and not (
        math.isfinite(method.runtime_s) and method.runtime_s >= 0
    ):
        problems.append(f"runtime_s: expected seconds >= 0, found {method.runtime_s}")
    if method.hardware is not None and len(method.hardware) > 200:
        problems.append("hardware: expected at most 200 characters")
    if len(method.description) > 20_000:
        problems.append("description: expected at most 20000 characters")
    if problems:
        raise InvalidInputError("; ".join(problems))
    return replace(
        method,
        name=method.name.strip(),
        hardware=method.hardware.strip() if method.hardware else None,
        description=method.description.strip(),
        paper_url=method.paper_url.strip(),
        code_url=method.code_url.strip(),
    )


def method_columns(method: MethodInfo) -> dict[str, Any]:
    """The submission row's columns for ``method``."""
    fields = method.to_dict()
    return {"method_name": fields["name"]} | {key: fields[key] for key in _SAME_NAME}


def method_of(submission: Submission) -> MethodInfo:
    """The method card stored on ``submission``."""
    fields = {key: getattr(submission, key) for key in _SAME_NAME}
    return MethodInfo.from_dict({"name": submission.method_name, **fields})
