"""docker-compose.yml and the Dockerfile, checked without a Docker engine.

The compose file is parsed (PyYAML) and interpolated with its own defaults; every
command, healthcheck and environment variable it names is then run through our real
command lines, with the named volumes standing in as folders under tmp_path.
"""
from __future__ import annotations

import fnmatch
import json
import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
import typer.main
import yaml
from typer.testing import CliRunner

import cuboidgen.cli
import cuboidtrain.cli
from cuboidtrain.train.monitor.status import Checkpoint, TrainerStatus, write_status
from shared.sample import encode
from shared.spool import SpoolWriter
from tests.conftest import build_sample

ROOT = Path(__file__).resolve().parents[1]
APPS = {"cuboidgen": cuboidgen.cli.app, "cuboidtrain": cuboidtrain.cli.app}
PREFIXES = {"cuboidgen": "CUBOIDGEN_", "cuboidtrain": "CUBOIDTRAIN_"}
# Service keys of the Compose Specification (compose-spec.json) this file may use: a typo
# such as `healtcheck` would otherwise be ignored by this test and rejected by Docker.
SERVICE_KEYS = {"build", "image", "init", "restart", "stop_grace_period", "shm_size", "depends_on", "volumes",
                "command", "entrypoint", "healthcheck", "environment", "profiles", "deploy", "hostname",
                "labels", "logging", "user", "working_dir", "cpus", "mem_limit"}
runner = CliRunner()


# --- reading the two files -----------------------------------------------------------------

def interpolate(value, env: dict[str, str]):
    """Compose's `${VAR}`, `${VAR:-default}`, `${VAR-default}` and `$$`, over a parsed tree."""
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if not isinstance(value, str):
        return value

    def one(m: re.Match) -> str:
        if m.group(0) == "$$":
            return "$"
        name, op, default = m.group("name"), m.group("op"), m.group("default") or ""
        assert name, f"unsupported interpolation {m.group(0)!r}"
        if op == ":-":
            return env.get(name) or default
        if op == "-":
            return env.get(name, default)
        assert op is None, f"unsupported interpolation {m.group(0)!r}"
        return env.get(name, "")

    return re.sub(r"\$\$|\$\{(?P<name>\w+)(?:(?P<op>:?-)(?P<default>[^}]*))?\}", one, value)


def load_compose(env: dict[str, str] | None = None) -> dict:
    raw = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    return interpolate(raw, env or {})


def parse_dockerfile() -> dict:
    """Stages, ARG names, the final stage's ENV values, COPY sources and CMD."""
    text = re.sub(r"\\\n", " ", (ROOT / "Dockerfile").read_text())
    stages, args, env, copies, cmd = [], set(), {}, [], None
    for line in text.splitlines():
        words = line.split()
        if not words or words[0].startswith("#"):
            continue
        instruction = words[0].upper()
        if instruction == "FROM" and len(words) == 4 and words[2].upper() == "AS":
            stages.append(words[3])
            env = {}  # a stage starts with its base image's environment, not the last stage's
        elif instruction == "ARG":
            args.add(words[1].split("=")[0])
        elif instruction == "ENV":
            env.update(pair.split("=", 1) for pair in words[1:] if "=" in pair)
        elif instruction == "COPY" and not words[1].startswith("--from"):
            copies += words[1:-1]
        elif instruction in ("CMD", "ENTRYPOINT"):
            cmd = json.loads(line.split(None, 1)[1])
    return {"text": text, "stages": stages, "args": args, "env": env, "copies": copies, "cmd": cmd}


def our_command(argv: list[str]) -> list[str]:
    """The `cuboidgen ...` / `cuboidtrain ...` part of an argv or shell line, up to a shell operator."""
    start = next(i for i, word in enumerate(argv) if word in APPS)
    end = next((i for i, word in enumerate(argv[start:], start) if word in ("||", "&&", ";", ">", "|")), len(argv))
    return argv[start:end]


def commands_of(service: dict, image_cmd: list[str]) -> list[list[str]]:
    """Every command of ours a service runs: its command (a shell script's lines too) and its healthcheck."""
    command = service.get("command") or image_cmd
    lines = command[2].splitlines() if command[:2] == ["sh", "-c"] else [shlex.join(command)]
    found = [our_command(shlex.split(line)) for line in lines if set(shlex.split(line)) & set(APPS)]
    test = service["healthcheck"]["test"]
    found.append(our_command(test[1:] if test[0] == "CMD" else shlex.split(test[1])))
    return found


def click_command(argv: list[str]):
    group = typer.main.get_command(APPS[argv[0]])
    return group.commands[argv[1]]


def envvars(program: str, command: str = "run") -> dict[str, str]:
    """Envvar -> option name of one of our commands."""
    return {p.envvar: p.name for p in click_command([program, command]).params if getattr(p, "envvar", None)}


def mounts(service: dict, volumes: dict[str, Path]) -> dict[str, Path]:
    """Container path -> the folder standing in for the named volume mounted there."""
    pairs = (v.split(":")[:2] for v in service.get("volumes", []))
    return {target: volumes[source] for source, target in pairs}


def on_host(value: str, where: dict[str, Path]) -> str:
    for target, folder in where.items():
        if value == target or value.startswith(target + "/"):
            return str(folder) + value[len(target):]
    return value


@pytest.fixture
def clean_env(monkeypatch):
    """No CUBOIDGEN_/CUBOIDTRAIN_ variable of the developer's shell may leak into a check."""
    for name in list(os.environ):
        if name.startswith(tuple(PREFIXES.values())):
            monkeypatch.delenv(name)
    return monkeypatch


@pytest.fixture
def volumes(tmp_path) -> dict[str, Path]:
    folders = {name: tmp_path / "volumes" / name for name in load_compose()["volumes"]}
    for folder in folders.values():
        folder.mkdir(parents=True)
    return folders


# --- the compose file ----------------------------------------------------------------------

def test_services_profiles_and_scaling():
    compose = load_compose()
    services = compose["services"]
    assert {"generator", "trainer", "trainer-gpu"} <= set(services)
    for name, service in services.items():
        assert set(service) <= SERVICE_KEYS, f"{name}: unknown keys {set(service) - SERVICE_KEYS}"
        assert service["restart"] in ("on-failure", "unless-stopped", "always"), name
        assert service["healthcheck"]["test"][0] in ("CMD", "CMD-SHELL"), name
    # `docker compose up` starts a generator and a CPU trainer; --scale generator=N needs
    # no fixed container name and no host port.
    assert "profiles" not in services["generator"] and "profiles" not in services["trainer"]
    assert "container_name" not in services["generator"] and "ports" not in services["generator"]
    assert services["trainer"]["environment"]["CUBOIDTRAIN_DEVICE"] == "cpu"
    # Every GPU reservation sits under a profile, so a machine without one can run `up`.
    for name, service in services.items():
        devices = service.get("deploy", {}).get("resources", {}).get("reservations", {}).get("devices", [])
        if any("gpu" in d.get("capabilities", []) for d in devices):
            assert service.get("profiles"), f"{name} reserves a GPU outside a profile"
    gpu = services["trainer-gpu"]
    assert gpu["profiles"] == ["gpu"] and gpu["environment"]["CUBOIDTRAIN_DEVICE"] == "cuda"
    assert gpu["deploy"]["resources"]["reservations"]["devices"][0]["driver"] == "nvidia"
    # The CUDA image must not overwrite the CPU one, nor the GPU run the CPU run.
    assert gpu["image"] != services["trainer"]["image"]
    assert gpu["environment"]["CUBOIDTRAIN_OUT"] != services["trainer"]["environment"]["CUBOIDTRAIN_OUT"]
    assert {v.split(":")[0] for s in services.values() for v in s["volumes"]} <= set(compose["volumes"])


def test_scaled_generators_do_not_share_a_seed():
    # N replicas with one CUBOIDGEN_SEED would all publish the same samples (under distinct names).
    compose = load_compose({"CUBOIDGEN_SEED": "7"})
    assert "CUBOIDGEN_SEED" not in compose["services"]["generator"]["environment"]


def test_both_daemons_share_the_spool_volume_where_their_spool_options_point():
    services = load_compose()["services"]
    spool_volume = {}
    for name, program in (("generator", "cuboidgen"), ("trainer", "cuboidtrain"), ("trainer-gpu", "cuboidtrain")):
        service = services[name]
        spool = service["environment"][f"{PREFIXES[program]}SPOOL"]
        by_target = {v.split(":")[1]: v.split(":")[0] for v in service["volumes"]}
        spool_volume[name] = by_target[spool]
        if program == "cuboidtrain":  # the run folder must outlive the container too
            out = service["environment"]["CUBOIDTRAIN_OUT"]
            assert any(out.startswith(target + "/") for target in by_target), f"{name}: {out} is on no volume"
    assert len(set(spool_volume.values())) == 1, spool_volume
    # One variable sets both daemons' size and shape (the trainer skips samples of another),
    # and their defaults agree.
    for env in ({}, {"CUBOID_SIZE": "128", "CUBOID_SHAPE": "twobox"}):
        services = load_compose(env)["services"]
        settings = {(services[name]["environment"][f"{prefix}SIZE"], services[name]["environment"][f"{prefix}SHAPE"])
                    for name, prefix in (("generator", "CUBOIDGEN_"), ("trainer", "CUBOIDTRAIN_"),
                                         ("trainer-gpu", "CUBOIDTRAIN_"))}
        assert settings == {(env.get("CUBOID_SIZE", "64"), env.get("CUBOID_SHAPE", "box"))}


def test_every_run_option_has_its_own_environment_variable():
    for program, prefix in PREFIXES.items():
        params = [p for p in click_command([program, "run"]).params if p.name != "help"]
        for p in params:
            assert p.envvar == f"{prefix}{p.name.upper()}", f"{program} run --{p.name}: envvar {p.envvar!r}"


def test_every_environment_variable_set_is_read_by_the_command_the_service_runs():
    compose, dockerfile = load_compose(), parse_dockerfile()
    for name, service in compose["services"].items():
        programs = {argv[0] for argv in commands_of(service, dockerfile["cmd"])}
        readable = {var for program in programs for var in envvars(program)}
        unread = set(service["environment"]) - readable
        assert not unread, f"{name} sets {sorted(unread)}, which none of {sorted(programs)} reads"
    readable = set(envvars("cuboidgen")) | set(envvars("cuboidtrain"))
    assert set(dockerfile["env"]) - {"PATH", "PYTHONUNBUFFERED"} <= readable


def test_every_command_and_healthcheck_is_a_valid_command_of_ours(clean_env):
    compose, dockerfile = load_compose(), parse_dockerfile()
    checked = []
    for name, service in compose["services"].items():
        for argv in commands_of(service, dockerfile["cmd"]):
            program, args = argv[0], argv[1:]
            result = runner.invoke(APPS[program], args + ["--help"])
            assert result.exit_code == 0, f"{name}: {shlex.join(argv)} --help: {result.output}"
            # Parse the real arguments with the service's environment: every option and
            # every value must be one the command accepts.
            for var, value in {**dockerfile["env"], **service["environment"]}.items():
                clean_env.setenv(var, str(value))
            command = click_command(argv)
            params = command.make_context(argv[1], list(args[1:])).params
            for var, value in service["environment"].items():
                if var in envvars(program, argv[1]) and value != "":
                    assert params[envvars(program, argv[1])[var]] is not None, f"{name}: {var} was not read"
            checked.append((name, argv[1]))
    assert ("generator", "run") in checked and ("generator", "health") in checked
    assert ("trainer", "run") in checked and ("trainer", "watch") in checked


def test_generator_service_runs_with_its_environment(clean_env, volumes):
    service = load_compose()["services"]["generator"]
    where = mounts(service, volumes)
    for var, value in service["environment"].items():
        clean_env.setenv(var, on_host(value, where))
    seen = []
    clean_env.setattr("cuboidgen.daemon.run", seen.append)
    argv = our_command(service["command"])
    result = runner.invoke(APPS[argv[0]], argv[1:])
    assert result.exit_code == 0, result.output
    (config,) = seen
    assert config.spool == volumes["spool"] and config.limit == 10_000 and config.max_samples is None
    assert config.workers == 1 and config.size == 64 and config.dashboard is False and config.seed is None


def run_trainer_script(service: dict, env: dict[str, str], tmp_path: Path) -> tuple[list[str], dict]:
    """Run the service's `sh -c` script with `cuboidtrain` stubbed: the argv and environment it execs."""
    stub_dir = tmp_path / "stub"
    stub_dir.mkdir(exist_ok=True)
    stub = stub_dir / "cuboidtrain"
    stub.write_text('#!/bin/sh\nprintf "%s\\n" "$@" > "$RECORD"\nenv >> "$RECORD.env"\n')
    stub.chmod(0o755)
    record = tmp_path / "record"
    path = f"{stub_dir}{os.pathsep}{os.environ['PATH']}"
    subprocess.run(service["command"], env={**env, "PATH": path, "RECORD": str(record)}, check=True, timeout=30)
    environment = dict(line.split("=", 1) for line in Path(f"{record}.env").read_text().splitlines() if "=" in line)
    Path(f"{record}.env").unlink()
    return ["cuboidtrain", *record.read_text().split()], environment


@pytest.mark.parametrize("name", ["trainer", "trainer-gpu"])
def test_trainer_service_starts_fresh_then_resumes(clean_env, volumes, tmp_path, name):
    service = load_compose()["services"][name]
    where = mounts(service, volumes)
    env = {var: on_host(value, where) for var, value in service["environment"].items()}
    seen = []

    def fake_training(config, dashboard=None):
        seen.append(config)
        return TrainerStatus(state="done", step=0, rank=0, last_checkpoint=Checkpoint(f"{config.out}/last.pt", 0))

    clean_env.setattr("cuboidtrain.train.loop.run", fake_training)
    for already_trained in (False, True):
        if already_trained:  # a restarted container finds the checkpoint of its last life
            Path(env["CUBOIDTRAIN_OUT"]).mkdir(parents=True, exist_ok=True)
            (Path(env["CUBOIDTRAIN_OUT"]) / "last.pt").write_bytes(b"")
        argv, environment = run_trainer_script(service, env, tmp_path)
        assert argv == ["cuboidtrain", "run"]
        ours = {k: v for k, v in environment.items() if k.startswith("CUBOIDTRAIN_")}
        result = runner.invoke(APPS["cuboidtrain"], argv[1:], env=ours)
        assert result.exit_code == 0, result.output
        config = seen[-1]
        assert config.resume is already_trained and config.overwrite is not already_trained
        assert Path(config.spool) == volumes["spool"] and Path(config.out).parent == volumes["runs"]
        assert config.device == service["environment"]["CUBOIDTRAIN_DEVICE"] and config.size == 64
        assert config.steps is None and config.init is None and config.dashboard is False


def test_generator_healthcheck_turns_healthy_once_this_host_publishes(clean_env, volumes):
    service = load_compose()["services"]["generator"]
    where = mounts(service, volumes)
    argv = [on_host(word, where) for word in our_command(service["healthcheck"]["test"][1:])]
    assert runner.invoke(APPS[argv[0]], argv[1:]).exit_code == 1  # an empty spool
    with SpoolWriter(volumes["spool"], limit=10) as writer:
        writer.publish(encode(build_sample(0, size=32)))
    result = runner.invoke(APPS[argv[0]], argv[1:])
    assert result.exit_code == 0 and "healthy" in result.output


def test_trainer_healthcheck_reads_the_run_status(clean_env, volumes):
    service = load_compose()["services"]["trainer"]
    where = mounts(service, volumes)
    out = Path(on_host(service["environment"]["CUBOIDTRAIN_OUT"], where))
    test = service["healthcheck"]["test"]
    assert test[0] == "CMD-SHELL"
    bin_dir = Path(sys.executable).parent  # the installed console scripts
    assert (bin_dir / "cuboidtrain").exists(), "pip install -e . first: the healthcheck runs the console script"
    env = {"PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "CUBOIDTRAIN_OUT": str(out),
           "HOME": os.environ.get("HOME", "/tmp")}

    def check() -> int:
        return subprocess.run(["sh", "-c", test[1]], env=env, capture_output=True, timeout=60).returncode

    assert check() == 1  # no status.json yet: watch's 2 is mapped to Docker's "unhealthy"
    write_status(out, TrainerStatus(state="training", pid=os.getpid(), updated=time.time()))
    assert check() == 0
    dead = subprocess.Popen(["true"])
    dead.wait()
    write_status(out, TrainerStatus(state="training", pid=dead.pid, updated=time.time()))
    assert check() == 1  # the trainer died mid-run
    write_status(out, TrainerStatus(state="done", pid=dead.pid, updated=time.time()))
    assert check() == 0


# --- the Dockerfile ------------------------------------------------------------------------

def test_compose_builds_what_the_dockerfile_defines():
    dockerfile, services = parse_dockerfile(), load_compose()["services"]
    variants = set(re.findall(r"(\w+)\) index=", dockerfile["text"]))
    assert variants == {"cpu", "cuda"}
    for name, service in services.items():
        build = service["build"]
        assert build["target"] in dockerfile["stages"], name
        assert set(build["args"]) <= dockerfile["args"], f"{name}: {set(build['args']) - dockerfile['args']}"
        assert build["args"]["TORCH_VARIANT"] in variants
        # Every setting a build may need on another network passes through from the shell.
        assert {"BASE_IMAGE", "TORCH_INDEX", "PYPI_INDEX", "BUILD_CA_CERTS", "BUILD_PIP_CONF"} <= set(build["args"]), name
    assert services["trainer-gpu"]["build"]["args"]["TORCH_VARIANT"] == "cuda"
    assert services["trainer"]["build"]["args"]["TORCH_VARIANT"] == "cpu"
    assert "-c constraints.txt" in dockerfile["text"]  # the tested pins
    # TORCH_VARIANT=cuda builds both daemons' image as the CUDA one, under its own name.
    services = load_compose({"TORCH_VARIANT": "cuda", "TORCH_INDEX": "https://mirror.example/cu",
                             "BUILD_CA_CERTS": "-----BEGIN CERTIFICATE-----"})["services"]
    for name in ("generator", "trainer"):
        assert services[name]["image"] == "cuboid-fit:cuda", name
        assert services[name]["build"]["args"]["TORCH_VARIANT"] == "cuda", name
        assert services[name]["build"]["args"]["TORCH_INDEX"] == "https://mirror.example/cu", name
        assert services[name]["build"]["args"]["BUILD_CA_CERTS"].startswith("-----BEGIN"), name


def build_stage_instructions() -> list[str]:
    text = parse_dockerfile()["text"]
    stage = text.split(" AS build", 1)[1].split(" AS runtime", 1)[0]
    return [line.strip() for line in stage.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def test_dockerfile_pins_torch_as_constraints_txt_does():
    pins = dict(line.split("==") for line in (ROOT / "constraints.txt").read_text().splitlines()
                if "==" in line and not line.startswith("#"))
    defaults = dict(re.findall(r"^ARG (TORCH\w*_VERSION)=(\S+)$", parse_dockerfile()["text"], re.M))
    assert defaults == {"TORCH_VERSION": pins["torch"], "TORCHVISION_VERSION": pins["torchvision"]}


def test_dockerfile_installs_torch_before_copying_anything():
    # The torch layer's cache key must not hash a file of the context: docker-compose v1 (docker-py)
    # and the docker CLI send differently made tars, so a COPY above it made every build redo torch.
    lines = build_stage_instructions()
    torch_layer = next(i for i, line in enumerate(lines) if line.startswith("RUN") and "torch==" in line)
    first_copy = next(i for i, line in enumerate(lines) if line.startswith("COPY"))
    assert torch_layer < first_copy
    # torch and torchvision come from TORCH_INDEX alone (no --extra-index-url to fall back on,
    # which brought PyPI's CUDA build into the cpu image), and the variant is checked after.
    torch_run = lines[torch_layer]
    assert "--extra-index-url" not in torch_run and "--no-deps --index-url \"$index\"" in torch_run
    assert "torch.version.cuda" in torch_run and "download.pytorch.org/whl/cpu" in torch_run


def test_dockerfile_and_compose_carry_nothing_of_a_particular_machine():
    # Indexes, certificates and pip settings are build arguments, given at build time; their
    # defaults name only public hosts, and the CA and pip configuration default to nothing.
    text = (ROOT / "Dockerfile").read_text() + (ROOT / "docker-compose.yml").read_text()
    hosts = set(re.findall(r"https?://([^/\s\"'}]+)", text))
    assert hosts <= {"pypi.org", "download.pytorch.org"}, hosts
    assert "file://" not in text and "BEGIN CERTIFICATE" not in text
    assert re.search(r"^ARG BUILD_CA_CERTS=$", text, re.M) and re.search(r"^ARG BUILD_PIP_CONF=$", text, re.M)
    runtime = parse_dockerfile()["text"].split(" AS runtime", 1)[1]
    assert "BUILD_CA_CERTS" not in runtime and "/opt/build" not in runtime  # the build stage's alone


def test_trainer_does_not_wait_for_a_healthy_generator():
    # A generator with CUBOIDGEN_MAX_SAMPLES may exit 0 before its first healthcheck, and an
    # exited container never turns healthy: the trainer starts beside it and waits for samples.
    services = load_compose({"CUBOIDGEN_MAX_SAMPLES": "8"})["services"]
    for name in ("trainer", "trainer-gpu"):
        assert services[name]["depends_on"]["generator"]["condition"] == "service_started", name
        assert "CUBOIDTRAIN_MAX_WAIT" in services[name]["environment"], name
        assert services[name]["environment"]["CUBOIDTRAIN_MAX_WAIT"] == ""  # wait on, by default
    assert services["generator"]["environment"]["CUBOIDGEN_MAX_SAMPLES"] == "8"
    assert services["generator"]["restart"] == "on-failure"  # a finished generator stays down


def test_healthcheck_interval_can_be_shortened():
    for env, expected in (({}, {"generator": "30s", "trainer": "60s"}),
                          ({"CUBOID_HEALTH_INTERVAL": "5s"}, {"generator": "5s", "trainer": "5s"})):
        services = load_compose(env)["services"]
        assert {name: services[name]["healthcheck"]["interval"] for name in expected} == expected


def test_dockerfile_default_command_parses(clean_env):
    dockerfile = parse_dockerfile()
    argv = dockerfile["cmd"]
    for var, value in dockerfile["env"].items():
        clean_env.setenv(var, value)
    params = click_command(argv).make_context(argv[1], argv[2:]).params
    assert str(params["spool"]) == dockerfile["env"]["CUBOIDGEN_SPOOL"]


def test_dockerfile_copies_every_package_and_dockerignore_keeps_them():
    dockerfile = parse_dockerfile()
    ignored = [line.strip() for line in (ROOT / ".dockerignore").read_text().splitlines()
               if line.strip() and not line.startswith("#")]
    for source in dockerfile["copies"]:
        assert (ROOT / source).exists(), f"COPY {source}: no such file in the repository"
        hit = [p for p in ignored if fnmatch.fnmatch(source, p) or fnmatch.fnmatch(source, p.removeprefix("**/"))]
        assert not hit, f"COPY {source} is excluded by .dockerignore {hit}"
    # pyproject's readme must be in the context too, or `pip install .` fails.
    packages = {p.name for p in ROOT.iterdir() if (p / "__init__.py").exists() and p.name != "tests"}
    assert packages <= set(dockerfile["copies"]) and "README.md" in dockerfile["copies"]
    for heavy in (".venv", "data_spool", "spools", "runs", ".git"):
        assert heavy in ignored
