"""The `dynrecon` command's startup: `--help` loads no stage, and the listed commands are the registered ones."""

from __future__ import annotations

import argparse
import importlib
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from dynrecon import cli

HEAVY = ("numpy", "scipy", "cv2", "pycolmap", "rerun", "tqdm")


def _loaded_after(argv: list[str]) -> set[str]:
    code = (
        "import sys\nfrom dynrecon.cli import main\ntry:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
        "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})), file=sys.stderr)"
    )
    done = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, check=True)
    return set(done.stderr.split())


@pytest.mark.parametrize("argv", [["--help"], ["--version"], []])
def test_the_command_list_loads_no_stage(argv: list[str]) -> None:
    loaded = _loaded_after(argv)
    assert not loaded & set(HEAVY), f"`dynrecon {' '.join(argv)}` imports {sorted(loaded & set(HEAVY))}"


def test_a_light_command_loads_only_its_stage() -> None:
    loaded = _loaded_after(["track", "--help"])
    assert not loaded & {"scipy", "pycolmap", "rerun"}


@pytest.mark.parametrize(
    "module_name", [m for m in cli.COMMAND_MODULES if hasattr(importlib.import_module(m), "COMMANDS")]
)
def test_listed_commands_are_the_registered_ones(module_name: str) -> None:
    """`COMMANDS` (what `dynrecon --help` lists without loading the module's parsers) matches `add_commands`."""
    module = importlib.import_module(module_name)
    parser = argparse.ArgumentParser()
    subparsers = parser.add_subparsers()
    module.add_commands(subparsers)
    registered = {action.dest: action.help for action in subparsers._choices_actions}
    assert registered == module.COMMANDS
    assert list(registered) == list(module.COMMANDS)


def test_full_and_listed_parsers_agree() -> None:
    listed = cli.build_parser("")
    full = cli.build_parser()
    assert listed.format_help() == full.format_help()


def test_a_user_error_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    assert (
        cli.main(
            ["-q", "solve", "--cameras", "none.json", "--tracks", "none.csv", "--out", "o", "--max-iterations", "0"]
        )
        == 2
    )
    error = capsys.readouterr().err
    assert error.startswith("dynrecon solve: error: ") and error.count("\n") == 1


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["register", "a.mp4", "b.mp4", "--out", "o", "--offsets", "cam0"], "argument --offsets: 'cam0'"),
        (["solve", "--cameras"], "argument --cameras: expected one argument"),
        (["nosuch"], "invalid choice: 'nosuch'"),
    ],
)
def test_an_option_error_is_one_line(capsys: pytest.CaptureFixture[str], argv: list[str], message: str) -> None:
    with pytest.raises(SystemExit) as stop:
        cli.main(argv)
    assert stop.value.code == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and message in error and "--help)" in error and "usage:" not in error


def test_run_passes_known_offsets_to_register_or_to_the_calibration_import() -> None:
    from dynrecon.pipeline_cli import pipeline_options

    base = ["run", "cam1.mp4", "cam2.mp4", "--out", "ws", "--offsets", "cam1=0,cam2=0.1"]
    plain = pipeline_options(cli.build_parser().parse_args(base))
    assert plain.register.offsets == {"cam1": 0.0, "cam2": 0.1}
    assert plain.calibration_options.offsets == {"cam1": 0.0, "cam2": 0.1}
    # with a lab calibration the import writes them and registration (not run) never sees them
    calibrated = pipeline_options(cli.build_parser().parse_args([*base, "--calibration", "lab.toml"]))
    assert calibrated.register.offsets == {} and calibrated.calibration_options.offsets == {"cam1": 0.0, "cam2": 0.1}


def test_run_takes_registers_camera_motion() -> None:
    """register's hint for a tripod measured as moving names --camera-motion static, which run lacked."""
    from dynrecon.pipeline_cli import pipeline_options
    from sfm.options import CameraMotion

    base = ["run", "cam1.mp4", "cam2.mp4", "--out", "ws"]
    assert pipeline_options(cli.build_parser().parse_args(base)).register.camera_motion is CameraMotion.AUTO
    static = cli.build_parser().parse_args([*base, "--camera-motion", "static"])
    assert pipeline_options(static).register.camera_motion is CameraMotion.STATIC


def test_a_second_writer_of_one_folder_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Two processes writing one --out mixed their files, each told it succeeded: the second is refused."""
    from dynrecon.lock import OUTPUT_LOCK_NAME, OutputLock

    out = tmp_path / "out"
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # a live pid not ours
    try:
        out.mkdir()
        (out / OUTPUT_LOCK_NAME).write_text(json.dumps({"pid": holder.pid, "host": socket.gethostname(), "token": "x"}))
        args = ["solve", "--cameras", str(tmp_path / "c.json"), "--tracks", str(tmp_path / "t.csv"), "--out", str(out)]
        assert cli.main(args) == 2
        err = capsys.readouterr().err
        assert f"another dynrecon command (pid {holder.pid}) is using this folder" in err and err.count("\n") == 1
        assert (out / OUTPUT_LOCK_NAME).exists()  # not ours: left alone
    finally:
        holder.kill()
        holder.wait()
    # its owner gone, the lock is taken over; and released, with the folder made for it, when the command ends
    assert cli.main(args) == 2 and "c.json" in capsys.readouterr().err
    assert not (out / OUTPUT_LOCK_NAME).exists()
    with OutputLock(tmp_path / "fresh"):
        assert (tmp_path / "fresh" / OUTPUT_LOCK_NAME).exists()
    assert not (tmp_path / "fresh").exists()


def test_a_writer_of_the_folder_above_or_within_is_refused(tmp_path: Path) -> None:
    """`register --out WS/register` beside a running `run --out WS` (and the other way round) wrote the same files,
    both told they succeeded: the lock of the workspace above or a stage folder within refuses the second."""
    from dynrecon.lock import OUTPUT_LOCK_NAME, WORKSPACE_MARK, OutputLock, WorkspaceLockedError
    from dynrecon.pipeline_state import STATE_NAME

    assert WORKSPACE_MARK == STATE_NAME

    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # a live pid not ours
    owner = json.dumps({"pid": holder.pid, "host": socket.gethostname(), "token": "x"})
    try:
        ws = tmp_path / "ws"
        (ws / "register").mkdir(parents=True)
        (ws / OUTPUT_LOCK_NAME).write_text(owner)
        with OutputLock(ws / "register"):  # a folder above that is no workspace (no pipeline.json): unrelated
            pass
        (ws / "pipeline.json").write_text("{}")
        with pytest.raises(WorkspaceLockedError, match=r"is writing .*ws, which holds this folder"):
            OutputLock(ws / "register").acquire()
        assert not (ws / "register" / OUTPUT_LOCK_NAME).exists()  # its own lock released
        (ws / OUTPUT_LOCK_NAME).unlink()
        (ws / "register" / OUTPUT_LOCK_NAME).write_text(owner)
        with pytest.raises(WorkspaceLockedError, match=r"is writing .*register, which is within this folder"):
            OutputLock(ws).acquire()
        with OutputLock(tmp_path / "elsewhere"):  # an unrelated folder
            pass
        # a new workspace, before its run wrote pipeline.json: the run's lock says it writes a workspace
        new = tmp_path / "new"
        (new / "register").mkdir(parents=True)
        (new / OUTPUT_LOCK_NAME).write_text(json.dumps({**json.loads(owner), "workspace": True}))
        with pytest.raises(WorkspaceLockedError, match=r"is writing .*new, which holds this folder"):
            OutputLock(new / "register").acquire()
        (new / OUTPUT_LOCK_NAME).unlink()
        (new / "register" / OUTPUT_LOCK_NAME).write_text(owner)
        with OutputLock(new):  # a plain writer of the folder (`export --out new`) is no workspace's
            pass
        with pytest.raises(WorkspaceLockedError, match=r"is writing .*register, which is within this folder"):
            OutputLock(new, workspace=True).acquire()
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.parametrize(("quiet", "seen"), [(True, ["True", "-", "-"]), (False, ["False", "10.0", "10.0"])])
def test_progress_bars_follow_quiet_and_a_log_file(quiet: bool, seen: list[str]) -> None:
    """tqdm reads its TQDM_* settings when it is imported: -q hides the bars, and into a file (stderr not a terminal)
    they show after 10 s and redraw every 10 s, in the command's own process (set too late, neither held there)."""
    code = (
        "from dynrecon.cli import configure_logging\n"
        f"configure_logging(0, {quiet})\n"
        "from tqdm import tqdm\n"
        "bar = tqdm(range(3))\n"
        "print(bar.disable, getattr(bar, 'mininterval', '-'), getattr(bar, 'delay', '-'))\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("TQDM_")}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert done.stdout.split() == seen


def test_a_warning_repeated_word_for_word_is_said_once() -> None:
    """The solve's clocks run once per path it tries, each repeating its warnings: a command says each once (a
    5-video solve printed 25 warnings for 2 causes); other warnings, and information, are all said."""
    code = (
        "import logging\n"
        "from dynrecon.cli import configure_logging\n"
        "configure_logging(0, False)\n"
        "log = logging.getLogger('reconstruct.clocks.estimate')\n"
        "for _ in range(3):\n"
        "    log.warning('video %r has no times', 'cam0')\n"
        "    log.info('searching')\n"
        "log.warning('video %r has no times', 'cam1')\n"
        "logging.getLogger('sfm.stage').warning('video %r has no times', 'cam0')\n"
        "configure_logging(0, False)\n"  # the next command in the same process (a benchmark's) says them again
        "log.warning('video %r has no times', 'cam1')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stderr.splitlines() == [
        "W reconstruct.clocks.estimate: video 'cam0' has no times",
        "I reconstruct.clocks.estimate: searching",
        "I reconstruct.clocks.estimate: searching",
        "I reconstruct.clocks.estimate: searching",
        "W reconstruct.clocks.estimate: video 'cam1' has no times",
        "W sfm.stage: video 'cam0' has no times",
        "W reconstruct.clocks.estimate: video 'cam1' has no times",
    ]


def test_a_full_disk_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]):
    """No space left while a command writes: the machine's state, said in one line naming the file, not a
    traceback; other OS errors (a bug's) still raise."""
    import argparse
    import errno

    import dynrecon.cli as cli

    failure = OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "points3d.csv"))

    def fails(_: argparse.Namespace) -> int:
        raise failure

    class Parser:
        def parse_args(self, argv: list[str]) -> argparse.Namespace:
            return argparse.Namespace(command="export", func=fails, out=str(tmp_path), verbose=0, quiet=False)

    monkeypatch.setattr(cli, "build_parser", lambda *_: Parser())
    assert cli.main(["export"]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"dynrecon export: error: {tmp_path / 'points3d.csv'}: no space left on the device (free some, then run again)"
    )
    failure = OSError(errno.ENOSPC, "No space left on device")  # a failed write or flush: no file name
    assert cli.main(["export"]) == 2
    assert (
        capsys.readouterr()
        .err.strip()
        .endswith(f"error: {tmp_path}: no space left on the device (free some, then run again)")
    )
    failure = OSError(errno.EBADF, "Bad file descriptor")
    with pytest.raises(OSError, match="Bad file descriptor"):
        cli.main(["export"])
