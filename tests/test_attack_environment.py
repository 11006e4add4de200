"""The bad-input table, faults of the environment: Prefect's home unwritable, a Prefect server that does not answer,
an output on a read-only file system or refused to this user, a file-size limit (`ulimit -f`), a port in use, a
binary file where text is read, a parquet file truncated or holding CSV. Each is refused in one line naming the
variable, address or file and what to do, with no traceback and nothing written (`helpers_attack.assert_refused`)."""

from __future__ import annotations

import errno
import os
import resource
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from helpers_attack import Case, World, assert_refused, dataset_copy, good, named
from test_attack_paths import demo_file

# ----------------------------------------------------------------------------- Prefect's home and server


@pytest.mark.parametrize("command", ["run", "demo", "deploy"])
def test_an_unwritable_prefect_home_is_one_line(attack_world, tmp_path, monkeypatch, command):
    """PREFECT_HOME inside a regular file: no folder can be made there (as on a read-only mount); refused before
    Prefect starts (it took 98 s and printed 5,328 lines)."""
    monkeypatch.chdir(tmp_path)
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("x")
    # the commands set Prefect's variables for the process: keep them from reaching later tests
    monkeypatch.setattr(os, "environ", {**os.environ, "PREFECT_HOME": str(blocker / "prefect")})
    argv = {"run": ["run", "--config", attack_world.config], "demo": ["demo", "--output-dir", tmp_path / "demo"],
            "deploy": ["deploy", "--config", attack_world.config]}[command]
    assert_refused(attack_world, tmp_path, lambda world, tmp: Case(argv, (
        f"PREFECT_HOME {blocker / 'prefect'}: not a writable folder", "set PREFECT_HOME to a writable folder")))


def cli_error(argv: list, cwd: Path, env: dict[str, str] | None = None, preexec_fn=None) -> str:
    """Run the CLI with `argv` in a process of its own; check it exits 1 with one `error: ...` line (below any log
    lines) and no traceback; return that line."""
    done = subprocess.run([sys.executable, "-c", "from latent_steering_cli import app; app()", *map(str, argv)],
                          preexec_fn=preexec_fn, capture_output=True, text=True, timeout=300, cwd=cwd, check=False,
                          env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1", **(env or {})})
    errors = [line for line in done.stderr.splitlines() if line.startswith("error: ")]
    assert done.returncode == 1, (done.returncode, done.stderr[-3000:])
    assert len(errors) == 1 and "Traceback" not in done.stderr + done.stdout, done.stderr[-3000:]
    return errors[0]


@pytest.mark.parametrize("command", ["deploy", "run"])
def test_a_prefect_server_that_does_not_answer_is_one_line(attack_world, tmp_path, command):
    """PREFECT_API_URL on a port where nothing listens: refused before Prefect's client retries (279 lines)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # free again once closed: nothing answers there
    url = f"http://127.0.0.1:{port}/api"
    line = cli_error([command, "--config", attack_world.config], tmp_path, {"PREFECT_API_URL": url})
    assert f"PREFECT_API_URL {url}: no Prefect server answers there" in line and "prefect server start" in line, line


# ----------------------------------------------------------------------------- outputs the file system refuses

# commands each writing one output under the case's tmp_path (helpers_attack.good)
OUTPUT_COMMANDS = ["filter", "convert", "manifest", "split", "concept-map", "capture", "slice", "steer", "train-sae"]
REFUSALS = {errno.EROFS: ("Read-only file system", "the file system is read-only", "write elsewhere"),
            errno.EACCES: ("Permission denied", "permission denied", "choose another path")}


def refuse_writes_under(monkeypatch: pytest.MonkeyPatch, root: Path, number: int) -> None:
    """Make every folder made and every file opened for writing under `root` fail with `number` (EROFS: a read-only
    mount; EACCES: a folder this user may not write, which root cannot be shown with chmod)."""
    strerror = REFUSALS[number][0]

    def refused(path) -> bool:
        return Path(os.fsdecode(path)).absolute().is_relative_to(root)

    def mkdir(path, *args, **kwargs):
        if refused(path):
            raise OSError(number, strerror, os.fsdecode(path))
        return real_mkdir(path, *args, **kwargs)

    def open_(path, flags, *args, **kwargs):
        if flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT) and refused(path):
            raise OSError(number, strerror, os.fsdecode(path))
        return real_open(path, flags, *args, **kwargs)

    real_mkdir, real_open = os.mkdir, os.open
    monkeypatch.setattr(os, "mkdir", mkdir)
    monkeypatch.setattr(os, "open", open_)


@pytest.mark.parametrize("number", list(REFUSALS), ids=errno.errorcode.get)
@pytest.mark.parametrize("command", OUTPUT_COMMANDS)
def test_an_output_the_file_system_refuses_is_one_line(attack_world, tmp_path, monkeypatch, command, number):
    monkeypatch.chdir(tmp_path)
    refuse_writes_under(monkeypatch, tmp_path, number)
    assert_refused(attack_world, tmp_path, lambda world, tmp: Case(
        [command, *good(world, tmp)[command]], (str(tmp), *REFUSALS[number][1:])))


def test_a_file_size_limit_is_one_line(attack_world, tmp_path):
    """`ulimit -f` of 64 KiB: `convert`'s first large write fails with EFBIG (SIGXFSZ ignored), said in one line."""
    limit = 64 * 1024

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    line = cli_error(["convert", *good(attack_world, tmp_path)["convert"]], tmp_path, preexec_fn=limited)
    for name in (str(tmp_path / "dataset"), "file too large", "ulimit -f", "nothing was kept"):
        assert name in line, (name, line)
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- a port in use, binary text, bad parquet


def test_serve_on_a_port_in_use_is_one_line(attack_world, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        port = listener.getsockname()[1]
        argv = [str(word) for word in good(attack_world, tmp_path)["serve"]]
        argv[argv.index("--port") + 1] = str(port)
        assert_refused(attack_world, tmp_path, lambda world, tmp: Case(
            ["serve", *argv], (f"127.0.0.1:{port} is in use", "choose another port")))


def binary_api_key(world: World, tmp_path: Path) -> Case:
    key = tmp_path / "key.bin"
    key.write_bytes(b"\xff\xfe\x00binary")
    return Case(["serve", *good(world, tmp_path)["serve"], "--api-key-file", key],
                (str(key), "not a text file", "expected the api key"))


def binary_problem_info(world: World, tmp_path: Path) -> Case:
    """A demo file whose problem_info attribute is not UTF-8 text."""
    def edit(handle) -> str:
        handle["data"].attrs["problem_info"] = b"\xff\xfe{"
        return "problem_info is not valid JSON"
    return demo_file(world, tmp_path, edit)


def bad_parquet(kind: str, file: str, command: str = "manifest") -> object:
    """`command` of a dataset copy whose parquet `file` (a glob under the dataset) is cut short or holds CSV."""
    def attack(world: World, tmp_path: Path) -> Case:
        dataset = dataset_copy(world, tmp_path)
        path = sorted(dataset.glob(file))[0]
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2] if kind == "truncated" else b"episode_index,frame_index\n0,0\n")
        argv = [str(word) for word in good(world, tmp_path)[command]]
        argv[argv.index("--lerobot-root") + 1] = str(dataset)
        return Case([command, *argv], (str(path), "not a readable parquet file"))
    return named(f"{command}_{kind}_{file.split('/')[0]}_{Path(file).stem.replace('*', 'n')}", attack)


ATTACKS = [
    binary_api_key, binary_problem_info,
    bad_parquet("truncated", "data/*/*.parquet"), bad_parquet("csv", "data/*/*.parquet"),
    bad_parquet("truncated", "meta/tasks.parquet"), bad_parquet("csv", "meta/episodes/*/*.parquet"),
    bad_parquet("truncated", "data/*/*.parquet", "capture"), bad_parquet("csv", "data/*/*.parquet", "concept-map"),
]


@pytest.mark.parametrize("attack", ATTACKS, ids=lambda attack: attack.__name__)
def test_refused(attack_world, tmp_path, monkeypatch, attack):
    monkeypatch.chdir(tmp_path)
    assert_refused(attack_world, tmp_path, attack)
