"""The server's container: Dockerfile and compose.yaml, read always, built where an engine runs.

The first tests parse both files for what a deployment relies on (a non-root user, the
port, the data volume, a health check, PostgreSQL beside the server). The last two build
the image and start it (alone, then with compose and PostgreSQL) with Docker or Podman,
and skip where no container engine answers (a client without a daemon included).
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from semantic3d.server.settings import Settings

from .processes import free_port

ROOT = Path(__file__).resolve().parents[2]
DATA = "/data"
PORT = "8000"


def dockerfile_instructions() -> list[tuple[str, str]]:
    """``(INSTRUCTION, arguments)`` of the final stage, continuation lines joined."""
    text = (ROOT / "Dockerfile").read_text(encoding="utf-8")
    joined = re.sub(r"\\\n", " ", text)
    stages: list[list[tuple[str, str]]] = []
    for line in joined.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        instruction, _, arguments = line.partition(" ")
        if instruction.upper() == "FROM":
            stages.append([])
        stages[-1].append((instruction.upper(), arguments.strip()))
    return stages[-1]


def exec_form(arguments: str) -> list[str]:
    """The command of a ``CMD``/``HEALTHCHECK ... CMD`` in exec (JSON) form."""
    value = json.loads(arguments)
    assert isinstance(value, list), f"expected exec form, found {arguments!r}"
    return [str(item) for item in value]


def compose() -> dict[str, Any]:
    yaml = pytest.importorskip("yaml")
    loaded = yaml.safe_load((ROOT / "compose.yaml").read_text(encoding="utf-8"))
    assert isinstance(loaded, dict)
    return loaded


def test_the_image_runs_the_server_as_an_unprivileged_user_on_a_data_volume() -> None:
    final = dockerfile_instructions()
    values = {name: args for name, args in final}  # the last of each kind
    user = values["USER"].split(":")[0]
    assert user not in ("root", "0") and user.isdigit() and int(user) > 0
    assert values["EXPOSE"].split() == [PORT]
    assert exec_form(values["VOLUME"]) == [DATA]
    assert f"SEMANTIC3D_DATA_DIR={DATA}" in values["ENV"].split()
    assert exec_form(values["CMD"]) == [
        "semantic3d",
        "serve",
        "--host",
        "0.0.0.0",
        "--port",
        PORT,
    ]
    check = values["HEALTHCHECK"]
    assert "CMD" in check.split() and f"127.0.0.1:{PORT}/api/health" in check
    installs = [args for name, args in final if name == "RUN" and "pip install" in args]
    assert len(installs) == 1 and "[server,postgres]" in installs[0]
    # The user is set after every RUN (they may need root), and owns the data folder.
    order = [name for name, _ in final]
    assert len(order) - 1 - order[::-1].index("USER") > max(
        i for i, name in enumerate(order) if name == "RUN"
    )
    assert any(f"chown {values['USER']} {DATA}" in args for name, args in final if name == "RUN")


def test_the_build_context_holds_what_the_image_copies() -> None:
    ignored = (ROOT / ".dockerignore").read_text(encoding="utf-8").split()
    copied = []
    for instruction in (ROOT / "Dockerfile").read_text(encoding="utf-8").splitlines():
        words = instruction.split()
        if words[:1] == ["COPY"] and not words[1].startswith("--from"):
            copied += words[1:-1]
    assert copied and all((ROOT / name).exists() for name in copied)
    assert "*" in ignored and all(f"!{name.rstrip('/')}" in " ".join(ignored) for name in copied)


def test_compose_runs_server_and_worker_on_postgresql() -> None:
    services = compose()["services"]
    db = services["db"]
    assert str(db["image"]).startswith("postgres:")
    assert "pg_isready" in " ".join(db["healthcheck"]["test"])
    for name in ("server", "worker"):
        service = services[name]
        assert service["build"] == "." and service["depends_on"]["db"]["condition"] == (
            "service_healthy"
        )
        assert [v for v in service["volumes"] if v.split(":")[1] == DATA], service["volumes"]
        url = service["environment"]["SEMANTIC3D_DATABASE_URL"]
        assert url.startswith("postgresql+psycopg://") and "@db/" in url
        assert "${POSTGRES_PASSWORD" in url  # no password written into the file
        assert set(service["environment"]) <= {
            f"SEMANTIC3D_{n.upper()}" for n in Settings.model_fields
        }
    assert services["server"]["command"][:2] == ["semantic3d", "serve"]
    assert services["server"]["ports"][0].endswith(f":{PORT}")
    assert services["server"]["ports"][0].startswith("127.0.0.1:")  # for a proxy on the host
    assert services["worker"]["command"] == ["semantic3d", "worker"]
    assert services["worker"]["healthcheck"] == {"disable": True}  # it serves no HTTP
    assert set(compose()["volumes"]) == {"data", "db-data"}


def test_the_licence_ships_with_the_package() -> None:
    licence = (ROOT / "LICENSE").read_text(encoding="utf-8")
    assert licence.startswith("MIT License") and "semantic3d developers" in licence
    project = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert 'license = "MIT"' in project
    # hatchling puts LICENSE into the sdist and the wheel's .dist-info/licenses/ unless
    # the build configuration leaves it out.
    assert "exclude" not in project.partition("[tool.hatch")[2].partition("[tool.pytest")[0]


def test_the_sdist_and_the_wheel_hold_the_licence(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Built as pip builds them (the project's build backend, called in the repository).
    backend = pytest.importorskip("hatchling.build")
    import tarfile
    import zipfile

    monkeypatch.chdir(ROOT)
    sdist = tmp_path / backend.build_sdist(str(tmp_path))
    wheel = tmp_path / backend.build_wheel(str(tmp_path))
    licence = (ROOT / "LICENSE").read_bytes()
    with tarfile.open(sdist) as archive:
        top = sdist.name.removesuffix(".tar.gz")
        member = archive.extractfile(f"{top}/LICENSE")
        assert member is not None and member.read() == licence
    with zipfile.ZipFile(wheel) as archive:
        (name,) = [n for n in archive.namelist() if n.endswith(".dist-info/licenses/LICENSE")]
        assert archive.read(name) == licence


# With a container engine -----------------------------------------------------------------


def container_engine() -> str | None:
    """Docker or Podman, when its engine answers (a bare client does not count)."""
    for name in ("docker", "podman"):
        path = shutil.which(name)
        if path is None:
            continue
        try:
            answered = subprocess.run([path, "info"], capture_output=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            continue
        if answered.returncode == 0:
            return path
    return None


def engine_or_skip() -> str:
    engine = container_engine()
    if engine is None:
        pytest.skip("no container engine answers (docker/podman info failed)")
    return engine


def run(*args: str, timeout: float = 120, check: bool = True) -> str:
    done = subprocess.run(list(args), capture_output=True, text=True, timeout=timeout)
    if check and done.returncode != 0:
        raise AssertionError(f"{shlex.join(args)} exited {done.returncode}:\n{done.stderr}")
    return done.stdout.strip()


def wait_for_health(url: str, timeout_s: float = 180) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if httpx.get(url + "/api/health", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(1)
    raise AssertionError(f"{url} not healthy within {timeout_s} s")


@pytest.fixture
def image() -> Iterator[tuple[str, str]]:
    """``(engine, tag)`` of the image built from this checkout; removed afterwards."""
    engine = engine_or_skip()
    tag = f"semantic3d-test-{uuid.uuid4().hex[:12]}"
    # Podman writes OCI images by default, which have no HEALTHCHECK: ask for Docker's.
    formats = ["--format", "docker"] if Path(engine).name == "podman" else []
    run(engine, "build", *formats, "--tag", tag, str(ROOT), timeout=1800)
    try:
        yield engine, tag
    finally:
        run(engine, "rmi", "--force", tag, check=False)


@pytest.mark.slow
def test_the_image_serves_and_keeps_its_data_on_the_volume(image: tuple[str, str]) -> None:
    engine, tag = image
    volume = f"{tag}-data"
    name = f"{tag}-server"
    port = free_port()

    def start() -> None:
        run(
            engine, "run", "--detach", "--name", name, "--publish", f"127.0.0.1:{port}:{PORT}",
            "--volume", f"{volume}:{DATA}", "--health-interval", "2s", tag,
        )  # fmt: skip
        wait_for_health(f"http://127.0.0.1:{port}")

    try:
        start()
        assert run(engine, "exec", name, "id", "-u") != "0"
        assert {"semantic3d.sqlite3", "secret_key"} <= set(
            run(engine, "exec", name, "ls", DATA).split()
        )
        key = run(engine, "exec", name, "cat", f"{DATA}/secret_key")
        deadline = time.monotonic() + 60
        while run(engine, "inspect", "--format", "{{.State.Health.Status}}", name) != "healthy":
            assert time.monotonic() < deadline, "the image's HEALTHCHECK never passed"
            time.sleep(1)
        run(engine, "rm", "--force", name)
        start()  # a new container on the same volume finds the same data
        assert run(engine, "exec", name, "cat", f"{DATA}/secret_key") == key
    finally:
        run(engine, "rm", "--force", name, check=False)
        run(engine, "volume", "rm", "--force", volume, check=False)


@pytest.mark.slow
def test_compose_serves_with_postgresql(tmp_path: Path) -> None:
    engine = engine_or_skip()
    if subprocess.run([engine, "compose", "version"], capture_output=True).returncode != 0:
        pytest.skip(f"{engine} has no compose")
    project = f"semantic3d-test-{uuid.uuid4().hex[:12]}"
    port = free_port()
    env_file = tmp_path / "compose.env"
    env_file.write_text(f"POSTGRES_PASSWORD={uuid.uuid4().hex}\nSERVER_PORT={port}\n")
    base = [engine, "compose", "--project-name", project, "--env-file", str(env_file)]
    base += ["--file", str(ROOT / "compose.yaml")]
    try:
        run(*base, "up", "--detach", "--build", "--wait", "--wait-timeout", "600", timeout=2400)
        wait_for_health(f"http://127.0.0.1:{port}")
        assert run(*base, "exec", "-T", "server", "id", "-u") != "0"
        settings_probe = (
            "from semantic3d.server.settings import load_settings as s; print(s().is_sqlite)"
        )
        assert run(*base, "exec", "-T", "server", "python", "-c", settings_probe) == "False"
        running = run(*base, "ps", "--status", "running", "--services").split()
        assert set(running) == {"db", "server", "worker"}
    finally:
        run(*base, "down", "--volumes", "--rmi", "local", timeout=600, check=False)
