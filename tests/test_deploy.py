"""deploy/: the compose files' rules, the Dockerfile's, the container entry point, the health
check and the cluster comparison. Fast; the real containers run in `make cluster-test`."""
from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import socket
import subprocess
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
COMPOSE_FILES = (DEPLOY / "docker-compose.yml", DEPLOY / "docker-compose.host.yml")
SECRET_WORDS = re.compile(r"(?i)password|passwd|secret|token|api[_-]?key|private[_-]?key|BEGIN [A-Z ]*PRIVATE KEY")
KEY_LIKE = re.compile(r"^[A-Za-z0-9+/=.:\-^!*?&<>()\[\]{}@%$#]{32,}$")  # base64, hex, Z85 (CURVE)
SUBPROCESS_TIMEOUT = 60  # seconds


def load_module(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def with_defaults(text: str) -> str:
    """Compose interpolation with every variable unset: ``${NAME:-default}`` -> ``default``."""
    return re.sub(r"\$\{\w+:?-([^}]*)\}", r"\1", text)


def scalars(node):
    if isinstance(node, dict):
        for k, v in node.items():
            yield str(k)
            yield from scalars(v)
    elif isinstance(node, list):
        for v in node:
            yield from scalars(v)
    elif node is not None:
        yield str(node)


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_config_is_valid(path):
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.skip("docker-compose is not installed")
    env = {k: v for k, v in os.environ.items() if not k.startswith("MOCAP_")}
    done = subprocess.run([exe, "-f", str(path), "config", "-q"], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=SUBPROCESS_TIMEOUT)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize("path", COMPOSE_FILES, ids=lambda p: p.name)
def test_compose_rules(path):
    text = path.read_text()
    doc = yaml.safe_load(text)
    assert str(doc["version"]) == "3.8", "docker-compose v1 needs the version line"
    services = doc["services"]
    assert set(services) == {"server", "client"}
    for name, svc in services.items():
        assert "container_name" not in svc, f"{name}: container_name breaks --scale"
        assert svc.get("init") is True, f"{name}: init: true forwards SIGTERM and reaps zombies"
        assert any(str(v).endswith(":/data") for v in svc.get("volumes", [])), f"{name}: /data volume"
        assert "${MOCAP_DATA" in text
        user = with_defaults(str(svc.get("user", "")))
        assert user and user.split(":")[0] not in ("0", "root"), f"{name}: runs as root"
        assert svc["image"].startswith("${MOCAP_IMAGE")

    server, client = services["server"], services["client"]
    assert server["healthcheck"]["test"], "the server needs a healthcheck"
    assert "ports" not in client, "a published port on the scaled service collides"
    # the server's address comes from the environment, never from the client's command
    assert "MOCAP_SERVER" in client["environment"]
    assert not any("tcp://" in str(a) for a in client["command"])
    assert client["command"][0] == "client"
    assert server["command"][0] == "server" and "--bind" in server["command"]
    assert "--min-clients" in server["command"]

    for value in scalars(doc):
        assert not SECRET_WORDS.search(value), f"secret-looking text in {path.name}: {value!r}"
        assert not KEY_LIKE.match(value), f"key-looking value in {path.name}: {value!r}"
    assert "secrets" not in doc


def test_host_variant_stays_on_loopback():
    doc = yaml.safe_load((DEPLOY / "docker-compose.host.yml").read_text())
    for svc in doc["services"].values():
        assert svc["network_mode"] == "host"
        assert "ports" not in svc
    bind = doc["services"]["server"]["command"][doc["services"]["server"]["command"].index("--bind") + 1]
    assert bind.startswith("tcp://127.0.0.1:")
    assert doc["services"]["client"]["environment"]["MOCAP_SERVER"].startswith("tcp://127.0.0.1:")


def test_bridge_variant_publishes_on_loopback_by_default():
    server = yaml.safe_load((DEPLOY / "docker-compose.yml").read_text())["services"]["server"]
    assert server["ports"] == ["${MOCAP_PUBLISH:-127.0.0.1:5555}:5555"]
    assert "network_mode" not in server


def test_dockerfile_rules():
    text = (DEPLOY / "Dockerfile").read_text()
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    assert lines[0] == "ARG BASE=python:3.11-slim-bookworm"
    assert any(line.startswith("FROM ${BASE}") for line in lines)
    for package in ("libegl1", "libgl1", "libgl1-mesa-dri", "python3-venv"):
        assert package in text
    users = [line.split()[1] for line in lines if line.startswith("USER ")]
    assert users and users[-1] not in ("root", "0")
    entry = [line for line in lines if line.startswith("ENTRYPOINT")][-1]
    assert json.loads(entry.split(None, 1)[1])  # exec form: a JSON list, no shell as PID 1
    assert "update-ca-certificates" in text and "deploy/extra/ca/" in text


def test_build_inputs_are_ignored_by_git():
    if not (REPO / ".git").exists() or shutil.which("git") is None:
        pytest.skip("not a git checkout")
    for path in ("deploy/extra/ca/proxy.crt", "deploy/extra/wheels/numpy.whl", "deploy/data/result"):
        done = subprocess.run(["git", "check-ignore", "-q", path], cwd=REPO, timeout=SUBPROCESS_TIMEOUT)
        assert done.returncode == 0, f"{path} is not ignored by git"


@pytest.mark.parametrize("script", ["cluster.sh", "base-image.sh", "entrypoint.sh"])
def test_scripts_parse(script):
    shell = "sh" if script == "entrypoint.sh" else "bash"
    path = DEPLOY / script
    assert os.access(path, os.X_OK), f"{script} must be executable"
    subprocess.run([shell, "-n", str(path)], check=True, timeout=SUBPROCESS_TIMEOUT)


def run_entrypoint(tmp_path, args, env=None):
    fake = tmp_path / "mocap"
    fake.write_text('#!/bin/sh\nfor a in "$@"; do echo "$a"; done\n')
    fake.chmod(0o755)
    script = tmp_path / "entrypoint.sh"
    script.write_text((DEPLOY / "entrypoint.sh").read_text().replace("/opt/mocap/bin/mocap", str(fake)))
    out = subprocess.run(["sh", str(script), *args], env={"PATH": os.environ["PATH"], **(env or {})},
                         capture_output=True, text=True, timeout=SUBPROCESS_TIMEOUT, check=True)
    return out.stdout.splitlines()


def test_entrypoint_client_takes_server_from_environment(tmp_path):
    argv = run_entrypoint(tmp_path, ["client", "-q"], {"MOCAP_SERVER": "tcp://server:5555"})
    assert argv[0] == "client" and argv[-1] == "-q"
    assert argv[argv.index("--connect") + 1] == "tcp://server:5555"
    name = argv[argv.index("--id") + 1]
    other = run_entrypoint(tmp_path, ["client"], {"MOCAP_SERVER": "tcp://server:5555"})
    assert other[other.index("--id") + 1] != name, "client names must differ between containers"


def test_entrypoint_keeps_explicit_arguments(tmp_path):
    argv = run_entrypoint(tmp_path, ["client", "--connect", "tcp://a:1", "--id", "c1"], {"MOCAP_SERVER": "tcp://b:2"})
    assert argv == ["client", "--connect", "tcp://a:1", "--id", "c1"]
    assert run_entrypoint(tmp_path, ["fit", "seq", "--out", "res"]) == ["fit", "seq", "--out", "res"]


def test_healthcheck_sees_a_listening_port():
    health = load_module("deploy_healthcheck", DEPLOY / "healthcheck.py")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        assert not health.listening(port)
        s.listen()
        assert health.listening(port)


def write_result(folder: Path, params: dict[int, list[float]], extra_frames=()):
    folder.mkdir(parents=True)
    rows = [{"frame": f, "params": p} for f, p in params.items()] + [{"frame": f, "params": params[f]}
                                                                      for f in extra_frames]
    (folder / "poses.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return folder


def test_compare_accepts_equal_and_rejects_different_runs(tmp_path):
    compare = load_module("deploy_compare", DEPLOY / "compare.py")
    ref = {0: [0.0, 1.0], 1: [0.5, -0.25]}
    single = write_result(tmp_path / "single", ref)
    same = write_result(tmp_path / "same", {1: ref[1], 0: ref[0]})
    assert compare.check(single, same, 2, 1e-9) == ([], 0.0)

    near = write_result(tmp_path / "near", {0: ref[0], 1: [0.5 + 1e-6, -0.25]})
    problems, worst = compare.check(single, near, 2, 1e-9)
    assert worst == pytest.approx(1e-6) and any("differ" in p for p in problems)

    twice = write_result(tmp_path / "twice", ref, extra_frames=[1])
    assert any("twice" in p for p in compare.check(single, twice, 2, 1e-9)[0])

    short = write_result(tmp_path / "short", {0: ref[0]})
    assert any("lacks frames [1]" in p for p in compare.check(single, short, 2, 1e-9)[0])
