"""A finalize killed between moving the zip and committing its row loses nothing.

The kill is real: a child process finalizes an upload and is SIGKILLed at the moment the
file has moved into ``submissions/`` and the submission row is not yet written. The next
start gives the file back to its upload, which then finalizes and evaluates as usual.
"""

from __future__ import annotations

import fcntl
import signal
import subprocess
import sys
from pathlib import Path

from sqlalchemy import func, select

from semantic3d.server.app import create_app
from semantic3d.server.models import Submission, UploadSession
from semantic3d.server.services.recovery import RecoveredFiles, recover_stored_files

from .conftest import Harness, ground_truth_arrays, noisy_predictions, submission_zip
from .processes import environment

# Finalizes one upload and SIGKILLs itself when the commit starts: the zip is then in
# submissions/ and no row names it (the gap a crash can fall into).
FINALIZE_AND_DIE = """
import os, signal, sys
from pathlib import Path
from semantic3d.evaluation import MethodInfo
from semantic3d.server.db import create_db_engine, create_session_factory
from semantic3d.server.services import submissions
from semantic3d.server.services.challenges import ChallengeCache
from semantic3d.server.settings import Settings

settings = Settings(secret_key="test-secret-key-0123456789", submission_cooldown_h=0,
                    embedded_worker=False)
factory = create_session_factory(create_db_engine(settings))
upload_id = sys.argv[2]

def die_in_the_gap(*args, **kwargs):
    moved = (settings.submissions_dir / f"{upload_id}.zip").is_file()
    print("moved" if moved else "not moved", flush=True)
    os.kill(os.getpid(), signal.SIGKILL)

submissions.write_transaction = die_in_the_gap
submissions.finalize_upload(factory, settings, ChallengeCache(settings),
                            user_id=int(sys.argv[1]), upload_id=upload_id,
                            method=MethodInfo("killed"))
print("finalize returned", flush=True)
"""


def count(harness: Harness, model: type) -> int:
    with harness.state.factory() as session:
        return int(session.scalar(select(func.count()).select_from(model)) or 0)


def test_a_finalize_killed_in_the_gap_loses_no_upload(harness: Harness) -> None:
    settings = harness.settings
    token = harness.user_token("grace")
    data = submission_zip(noisy_predictions(ground_truth_arrays(), 0.9))
    upload_id = harness.upload(token, data)
    with harness.state.factory() as session:
        user_id = session.get_one(UploadSession, upload_id).user_id

    child = subprocess.run(
        [sys.executable, "-c", FINALIZE_AND_DIE, str(user_id), upload_id],
        env=environment(settings.data_dir),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert child.returncode == -signal.SIGKILL, child.stderr
    assert child.stdout.split() == ["moved"]
    stored = settings.submissions_dir / f"{upload_id}.zip"
    assert stored.is_file() and not (settings.uploads_dir / f"{upload_id}.part").exists()
    assert count(harness, Submission) == 0 and count(harness, UploadSession) == 1

    create_app(settings)  # the next start
    assert not stored.exists()
    headers = {"Authorization": f"Bearer {token}"}
    status = harness.client.get(f"/api/uploads/{upload_id}", headers=headers).json()
    assert status["complete"] and status["received_bytes"] == len(data)
    response = harness.finalize(token, upload_id)
    assert response.status_code == 201, response.text
    assert harness.work()
    with harness.state.factory() as session:
        submission = session.scalars(select(Submission)).one()
        assert submission.stored_name == f"{upload_id}.zip"
        assert submission.mean_iou is not None
    assert sorted(p.name for p in harness.stored_files()) == [f"{upload_id}.zip"]
    assert not settings.orphaned_dir.exists()


def test_stray_files_are_set_aside_and_busy_ones_left_alone(harness: Harness) -> None:
    settings = harness.settings
    token = harness.user_token("grace")
    accepted = harness.submit(token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)))
    assert accepted.status_code == 201
    kept = [p.name for p in settings.submissions_dir.iterdir()]
    unnamed = settings.submissions_dir / ("ab" * 16 + ".zip")  # an upload long gone
    unnamed.write_bytes(b"an interrupted finalize")
    foreign = settings.submissions_dir / "random-name.zip"  # not ours at all
    foreign.write_bytes(b"something else")
    busy = settings.submissions_dir / ("cd" * 16 + ".zip")  # a finalize in its gap, now
    busy.write_bytes(b"being finalized")
    with busy.open("rb") as held:
        fcntl.flock(held.fileno(), fcntl.LOCK_EX)
        recovered = recover_stored_files(harness.state.factory, settings)
    assert recovered.restored == ()
    assert sorted(recovered.set_aside) == sorted([unnamed.name, foreign.name])
    assert sorted(p.name for p in settings.orphaned_dir.iterdir()) == sorted(
        [unnamed.name, foreign.name]
    )
    assert (settings.orphaned_dir / unnamed.name).read_bytes() == b"an interrupted finalize"
    assert sorted(p.name for p in settings.submissions_dir.iterdir()) == sorted([*kept, busy.name])
    assert settings.orphaned_dir.stat().st_mode & 0o777 == 0o700
    # Once its holder is gone without committing a row, the busy file is a stray too.
    assert recover_stored_files(harness.state.factory, settings).set_aside == (busy.name,)
    assert recover_stored_files(harness.state.factory, settings) == RecoveredFiles()


def test_an_accepted_submission_is_stored_under_its_upload_id(harness: Harness) -> None:
    token = harness.user_token("grace")
    upload_id = harness.upload(token, submission_zip(noisy_predictions(ground_truth_arrays(), 0.9)))
    assert harness.finalize(token, upload_id).status_code == 201
    assert [p.name for p in harness.stored_files()] == [f"{upload_id}.zip"]
    assert Path(harness.settings.submissions_dir / f"{upload_id}.zip").is_file()
