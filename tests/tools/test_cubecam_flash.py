"""`cubecam flash` with fake `arduino-cli` and `pio` executables on PATH (small scripts that
log their arguments and answer `core list`, `lib list`, `board details`... as configured):
builder detection, the exact commands of both builders, every missing piece as one error line
with the command that fixes it, --dry-run, per-board failures (with real provisioning over
fake boards on ptys); and the PlatformIO project file and the FQBN against the real core."""

from __future__ import annotations

import configparser
import json
import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from fakeboard import FakeBoard
from toolcheck import REPO, assert_one_line_error, run_cubecam

from cubecam import boards
from cubecam.cli import main
from cubecam.flash import FQBN, GS2200_GIT_URL, PACKAGE_INDEX_URL

PIO = shutil.which("pio") or str(Path(sys.executable).parent / "pio")
VENDOR_CORE = REPO.parent / "shared" / "vendor" / "spresense" / "core-3.4.4"
EXPECTED_FQBN = "SPRESENSE:spresense:spresense:Core=Main,Memory=1536,UploadSpeed=921600,Debug=Disabled"

FAKE_TOOL = f"""#!{sys.executable} -S
import json, os, sys
here = os.path.dirname(os.path.abspath(__file__))
name = os.path.basename(sys.argv[0])
with open(os.path.join(here, "calls.jsonl"), "a") as log:
    log.write(json.dumps([name] + sys.argv[1:]) + "\\n")
with open(os.path.join(here, name + ".json")) as f:
    rules = json.load(f)
for rule in rules:
    if all(word in sys.argv[1:] for word in rule["when"]):
        sys.stdout.write(rule["stdout"])
        sys.stderr.write(rule["stderr"])
        sys.exit(rule["rc"])
"""


class FakeTools:
    """`arduino-cli` and `pio` in one folder put first on PATH; answers are rules matched on
    the words of the command line, newest first."""

    def __init__(self, root: Path):
        self.bin = root / "bin"
        self.bin.mkdir()
        self.sdk = root / "arduino15" / "packages" / "SPRESENSE" / "tools" / "spresense-sdk" / "3.4.4"
        self.firmware = self.sdk / "spresense" / "firmware"
        self.firmware.mkdir(parents=True)
        self.sketch = root / "cubecam"
        self.sketch.mkdir()
        (self.sketch / "cubecam.ino").write_text("void setup() {}\nvoid loop() {}\n")
        self.build_path = root / "build"
        self.project = root / "pio-project"
        self.project.mkdir()
        (self.project / "platformio.ini").write_text(
            "[env:spresense]\nplatform = https://github.com/maxgerhardt/platform-sonyspresense.git#dc6a593\n"
            "board = spresense\nframework = arduino\n")
        self.pio_core = root / "pio-core"
        (self.pio_core / "platforms" / "sonyspresense").mkdir(parents=True)
        (self.pio_core / "platforms" / "sonyspresense" / "platform.json").write_text('{"name": "sonyspresense"}')
        self.rules: dict[str, list[dict]] = {"arduino-cli": [], "pio": []}
        self.install("arduino-cli")
        self.install("pio")
        self.answer("arduino-cli", ["core", "list"], json.dumps(
            {"platforms": [{"id": "arduino:avr", "installed_version": "1.8.6"},
                           {"id": "SPRESENSE:spresense", "installed_version": "3.4.4"}]}))
        self.answer("arduino-cli", ["lib", "list"], json.dumps(
            {"installed_libraries": [{"library": {"name": "GS2200", "version": "1.2.3"}}]}))
        self.answer("arduino-cli", ["board", "details"], json.dumps(
            {"fqbn": "SPRESENSE:spresense:spresense",
             "build_properties": ["build.board=spresense_ast", f"runtime.tools.spresense-sdk.path={self.sdk}"]}))
        self.answer("pio", ["--version"], "PlatformIO Core, version 6.2.0\n")
        self.loader(required="v3.4.1", unpacked="v3.4.1")

    def install(self, tool: str) -> None:
        path = self.bin / tool
        path.write_text(FAKE_TOOL)
        path.chmod(0o755)
        self._save(tool)

    def remove(self, tool: str) -> None:
        (self.bin / tool).unlink()

    def answer(self, tool: str, when: list[str], stdout: str = "", rc: int = 0, stderr: str = "") -> None:
        self.rules[tool].insert(0, {"when": when, "stdout": stdout, "rc": rc, "stderr": stderr})
        self._save(tool)

    def _save(self, tool: str) -> None:
        (self.bin / f"{tool}.json").write_text(json.dumps(self.rules[tool]))

    def loader(self, required: str, unpacked: str | None) -> None:
        (self.firmware / "version.json").write_text(json.dumps(
            {"BoardName": "SPRESENSE", "LoaderVersion": required,
             "DownloadURL": "https://developer.sony.com/file/download/download-spresense-firmware-v3-4-1"}))
        stored = self.firmware / "stored_version.json"
        if unpacked is None:
            stored.unlink(missing_ok=True)
        else:
            stored.write_text(json.dumps({"LoaderVersion": unpacked}))

    def calls(self, tool: str | None = None) -> list[list[str]]:
        log = self.bin / "calls.jsonl"
        rows = [json.loads(line) for line in log.read_text().splitlines()] if log.exists() else []
        return rows if tool is None else [row[1:] for row in rows if row[0] == tool]

    def runs(self, tool: str) -> list[list[str]]:
        """The calls that build, upload or burn (not the read-only queries)."""
        queries = ({"--version"}, {"core", "list"}, {"lib", "list"}, {"board", "details"})
        return [c for c in self.calls(tool) if not any(q <= set(c) for q in queries)]

    # the exact commands of each builder
    def compile(self) -> list[str]:
        return [str(self.bin / "arduino-cli"), "compile", "--fqbn", EXPECTED_FQBN, "--build-path",
                str(self.build_path), str(self.sketch)]

    def upload(self, port: str) -> list[str]:
        return [str(self.bin / "arduino-cli"), "upload", "--fqbn", EXPECTED_FQBN, "--port", port, "--input-dir",
                str(self.build_path), str(self.sketch)]

    def burn(self, port: str) -> list[str]:
        return [str(self.bin / "arduino-cli"), "burn-bootloader", "--fqbn", EXPECTED_FQBN, "--port", port,
                "--programmer", "sfutools"]

    def pio_run(self, *extra: str) -> list[str]:
        return [str(self.bin / "pio"), "run", "-d", str(self.project), "-e", "spresense", *extra]

    def args(self, *extra: str) -> list[str]:
        return ["flash", "--sketch", str(self.sketch), "--build-path", str(self.build_path),
                "--project", str(self.project), *extra]


@pytest.fixture
def tools(tmp_path, monkeypatch) -> FakeTools:
    fake = FakeTools(tmp_path)
    monkeypatch.setenv("PATH", f"{fake.bin}{os.pathsep}/usr/bin{os.pathsep}/bin")
    monkeypatch.setenv("PLATFORMIO_CORE_DIR", str(fake.pio_core))
    return fake


def no_pio(tmp_path) -> list[str]:
    """Options that leave PlatformIO out (the venv's own pio would otherwise be found)."""
    return ["--pio", str(tmp_path / "no-pio")]


def stripped(calls: list[list[str]]) -> list[list[str]]:
    return [c[1:] for c in calls]


# --- builder detection and the exact commands ---


@pytest.mark.parametrize("core_list", [
    {"platforms": [{"id": "SPRESENSE:spresense", "installed_version": "3.4.4"}]},  # arduino-cli 1.x
    [{"id": "SPRESENSE:spresense", "installed": "3.4.4"}],                         # 0.18 ... 0.35
    [{"ID": "SPRESENSE:spresense", "Installed": "2.6.0"}],                         # up to 0.17
])
def test_auto_detect_prefers_arduino_cli_with_sonys_board_package(tools, capfd, core_list):
    tools.answer("arduino-cli", ["core", "list"], json.dumps(core_list))
    assert main(tools.args("--port", "/dev/ttyUSB0")) == 0
    assert tools.runs("arduino-cli") == stripped([tools.compile(), tools.upload("/dev/ttyUSB0")])
    assert tools.calls("pio") == []
    err = capfd.readouterr().err
    assert "building with arduino-cli (arduino-cli has Sony's board package SPRESENSE:spresense)" in err
    assert "/dev/ttyUSB0: flashed" in err


def test_auto_detect_uses_platformio_when_arduino_cli_lacks_the_board_package(tools, capfd):
    tools.answer("arduino-cli", ["core", "list"], json.dumps({"platforms": None}))
    assert main(tools.args("--port", "/dev/ttyUSB0")) == 0
    assert tools.runs("pio") == stripped([tools.pio_run(),
                                          tools.pio_run("-t", "upload", "--upload-port", "/dev/ttyUSB0")])
    assert tools.runs("arduino-cli") == []
    assert "building with platformio (arduino-cli lacks Sony's board package" in capfd.readouterr().err


def test_auto_detect_uses_platformio_without_arduino_cli(tools, capfd):
    tools.remove("arduino-cli")
    assert main(tools.args("--port", "/dev/ttyUSB3", "--burn-bootloader")) == 0
    assert tools.runs("pio") == stripped([
        tools.pio_run(),
        tools.pio_run("-t", "bootloader", "--upload-port", "/dev/ttyUSB3"),
        tools.pio_run("-t", "upload", "--upload-port", "/dev/ttyUSB3")])
    assert "building with platformio (arduino-cli not found)" in capfd.readouterr().err


def test_explicit_builder_overrides_detection(tools):
    assert main(tools.args("--port", "/dev/ttyUSB0", "--builder", "platformio", "--no-build")) == 0
    assert tools.runs("pio") == stripped([tools.pio_run("-t", "upload", "--upload-port", "/dev/ttyUSB0")])
    assert tools.calls("arduino-cli") == []


def test_burn_bootloader_runs_before_each_upload(tools):
    assert main(tools.args("--port", "/dev/ttyUSB0", "--burn-bootloader")) == 0
    assert tools.runs("arduino-cli") == stripped(
        [tools.compile(), tools.burn("/dev/ttyUSB0"), tools.upload("/dev/ttyUSB0")])


def test_fqbn_is_the_exact_one():
    assert FQBN == EXPECTED_FQBN


# --- missing pieces: one line, exit 1, the fixing command, nothing run ---


def test_missing_arduino_cli(tools, capfd):
    tools.remove("arduino-cli")
    rc = main(tools.args("--port", "/dev/ttyUSB0", "--builder", "arduino-cli"))
    assert_one_line_error(rc, capfd.readouterr().err, "arduino-cli not found",
                          "curl -fsSL https://raw.githubusercontent.com/arduino/arduino-cli/master/install.sh | "
                          "BINDIR=~/.local/bin sh", "--builder platformio")
    assert tools.calls() == []


def test_neither_builder_installed(tools, capfd, tmp_path):
    tools.remove("arduino-cli")
    tools.remove("pio")
    rc = main(tools.args("--port", "/dev/ttyUSB0", *no_pio(tmp_path)))
    assert_one_line_error(rc, capfd.readouterr().err, "neither arduino-cli nor PlatformIO (pio) is installed",
                          f"`{sys.executable} -m pip install platformio==6.2.0`")


@pytest.mark.parametrize("builder", ["arduino-cli", "auto"])
def test_missing_board_package(tools, capfd, tmp_path, builder):
    tools.answer("arduino-cli", ["core", "list"], json.dumps({"platforms": [{"id": "arduino:avr",
                                                                             "installed_version": "1.8.6"}]}))
    rc = main(tools.args("--port", "/dev/ttyUSB0", "--builder", builder, *no_pio(tmp_path)))
    assert_one_line_error(rc, capfd.readouterr().err, "board package (SPRESENSE:spresense) is not installed",
                          f"`arduino-cli config add board_manager.additional_urls {PACKAGE_INDEX_URL}`",
                          "`arduino-cli core update-index`", "`arduino-cli core install SPRESENSE:spresense`")
    assert tools.runs("arduino-cli") == []


def test_missing_gs2200_library(tools, capfd):
    tools.answer("arduino-cli", ["lib", "list"], json.dumps({"installed_libraries": None}))
    rc = main(tools.args("--port", "/dev/ttyUSB0"))
    assert_one_line_error(rc, capfd.readouterr().err, "GS2200-WiFi library",
                          "`arduino-cli config set library.enable_unsafe_install true`",
                          f"`arduino-cli lib install --git-url {GS2200_GIT_URL}`")
    assert GS2200_GIT_URL.endswith("#6126fb4f885e33aa6fe5399996493cf8ed21fe92")
    assert tools.runs("arduino-cli") == []


@pytest.mark.parametrize("unpacked", [None, "v2.4.0"])
def test_missing_bootloader_files(tools, capfd, unpacked):
    tools.loader(required="v3.4.1", unpacked=unpacked)
    rc = main(tools.args("--port", "/dev/ttyUSB0"))
    err = capfd.readouterr().err
    assert_one_line_error(rc, err, "bootloader v3.4.1 has not been installed from this machine",
                          "https://developer.sony.com/file/download/download-spresense-firmware-v3-4-1",
                          str(tools.firmware / "firmware.zip"), f"`{shlex.join(tools.burn('/dev/ttyUSB0'))}`")
    assert ("is for v2.4.0" if unpacked else "is missing") in err
    assert tools.runs("arduino-cli") == []


def test_bootloader_archive_in_place_lets_burn_bootloader_run(tools):
    tools.loader(required="v3.4.1", unpacked=None)
    (tools.firmware / "firmware.zip").write_bytes(b"PK\x05\x06" + bytes(18))
    assert main(tools.args("--port", "/dev/ttyUSB0", "--burn-bootloader")) == 0
    assert tools.runs("arduino-cli")[1] == tools.burn("/dev/ttyUSB0")[1:]


def test_no_bootloader_check(tools):
    tools.loader(required="v3.4.1", unpacked=None)
    assert main(tools.args("--port", "/dev/ttyUSB0", "--no-bootloader-check")) == 0
    assert not any("details" in c for c in tools.calls("arduino-cli"))
    assert tools.runs("arduino-cli") == stripped([tools.compile(), tools.upload("/dev/ttyUSB0")])


def test_not_a_sketch_folder(tools, capfd, tmp_path):
    rc = main(tools.args("--port", "/dev/ttyUSB0", "--sketch", str(tmp_path)))
    assert_one_line_error(rc, capfd.readouterr().err, f"{tmp_path / (tmp_path.name + '.ino')}: missing")
    assert tools.runs("arduino-cli") == []


def test_broken_arduino_cli(tools, capfd):
    tools.answer("arduino-cli", ["core", "list"], rc=3, stderr="Error initializing instance: no data dir\n")
    rc = main(tools.args("--port", "/dev/ttyUSB0"))
    assert_one_line_error(rc, capfd.readouterr().err, "core list --format json` exited 3",
                          "Error initializing instance: no data dir")


def test_missing_platformio_platform(tools, capfd):
    shutil.rmtree(tools.pio_core / "platforms")
    rc = main(tools.args("--port", "/dev/ttyUSB0", "--builder", "platformio"))
    assert_one_line_error(rc, capfd.readouterr().err, "Spresense platform for PlatformIO is not installed",
                          f"`pio pkg install -d {tools.project} -e spresense`")
    assert tools.runs("pio") == []


def test_without_platformio(tmp_path, capsys):
    rc = main(["flash", "--port", "/dev/ttyUSB0", "--builder", "platformio", *no_pio(tmp_path)])
    assert_one_line_error(rc, capsys.readouterr().err, "PlatformIO (pio) not found", "pip install platformio")


# --- failures while running ---


def test_build_failure_stops_before_any_upload(tools, capfd):
    tools.answer("arduino-cli", ["compile"], rc=1, stderr="cubecam.ino:3:1: expected unqualified-id\n")
    rc = main(tools.args("--port", "/dev/ttyUSB0"))
    assert_one_line_error(rc, capfd.readouterr().err, "build failed", "exited 1 (its output is above)")
    assert tools.runs("arduino-cli") == stripped([tools.compile()])


def test_upload_failure_mid_way_is_reported_per_board(tools, capfd, monkeypatch):
    ports = ["/dev/ttyUSB0", "/dev/ttyUSB1", "/dev/ttyUSB2"]
    monkeypatch.setattr(boards, "attached_boards", lambda: [boards.Board(p, "", "") for p in ports])
    tools.answer("arduino-cli", ["upload", "/dev/ttyUSB1"], rc=2, stderr="Please press RESET button\n")
    rc = main(tools.args("--all"))
    err = capfd.readouterr().err
    assert_one_line_error(rc, err, "1 of 3 board(s) failed: /dev/ttyUSB1: upload to /dev/ttyUSB1 failed",
                          "exited 2")
    assert tools.runs("arduino-cli") == stripped([tools.compile(), *(tools.upload(p) for p in ports)])
    assert "/dev/ttyUSB0: flashed" in err and "/dev/ttyUSB2: flashed" in err
    assert "/dev/ttyUSB1: FAILED: upload to /dev/ttyUSB1 failed" in err


def test_flash_then_provision_each_board_over_serial(tools, tmp_path, monkeypatch, capfd):
    """Three boards: one uploads and provisions, one fails its upload (so is not provisioned),
    one uploads but cannot join the network. Provisioning runs over real ptys."""
    password = tmp_path / "wifi.txt"
    password.write_text("hunter22\n")
    with FakeBoard(name="camA") as good, FakeBoard(name="camC", fail_ssids=("lab",)) as nojoin:
        bad = "/dev/ttyUSB9"
        ports = [good.path, bad, nojoin.path]
        monkeypatch.setattr(boards, "attached_boards", lambda: [boards.Board(p, "", "") for p in ports])
        tools.answer("arduino-cli", ["upload", bad], rc=1)
        rc = main(tools.args("--all", "--ssid", "lab", "--password-file", str(password), "--join-timeout", "5"))
        assert good.received_passwords == ["hunter22"] and good.online
        assert not nojoin.online
    err = capfd.readouterr().err
    assert_one_line_error(rc, err, "2 of 3 board(s) failed", f"{bad}: upload to {bad} failed",
                          f"{nojoin.path}: provisioning failed")
    assert "hunter22" not in err
    uploads = [c for c in tools.runs("arduino-cli") if c[0] == "upload"]
    assert [c[c.index("--port") + 1] for c in uploads] == ports


# --- dry run ---


def test_dry_run_prints_every_command_of_both_builders(tools, capfd, monkeypatch):
    monkeypatch.setattr(boards, "attached_boards", lambda: [boards.Board("/dev/ttyUSB0", "a", ""),
                                                            boards.Board("/dev/ttyUSB1", "b", "")])
    assert main(tools.args("--all", "--dry-run", "--burn-bootloader", "--ssid", "lab",
                           "--password-file", "/home/me/wifi.txt", "--fps", "7.5")) == 0
    lines = capfd.readouterr().out.splitlines()
    provision = [["cubecam", "provision", "--port", p, "--ssid", "lab", "--password-file", "/home/me/wifi.txt",
                  "--fps", "7.5"] for p in ("/dev/ttyUSB0", "/dev/ttyUSB1")]
    assert lines[0] == "# arduino-cli"
    split = lines.index("# platformio")
    assert [shlex.split(line) for line in lines[1:split]] == [
        tools.compile(), tools.burn("/dev/ttyUSB0"), tools.upload("/dev/ttyUSB0"),
        tools.burn("/dev/ttyUSB1"), tools.upload("/dev/ttyUSB1"), *provision]
    assert [shlex.split(line) for line in lines[split + 1:]] == [
        tools.pio_run(),
        tools.pio_run("-t", "bootloader", "--upload-port", "/dev/ttyUSB0"),
        tools.pio_run("-t", "upload", "--upload-port", "/dev/ttyUSB0"),
        tools.pio_run("-t", "bootloader", "--upload-port", "/dev/ttyUSB1"),
        tools.pio_run("-t", "upload", "--upload-port", "/dev/ttyUSB1"), *provision]
    assert tools.calls() == []  # nothing ran, not even a query


def test_dry_run_of_one_builder_without_tools(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("PATH", "/usr/bin:/bin")
    assert main(["flash", "--port", "/dev/ttyUSB0", "--dry-run", "--builder", "arduino-cli", "--no-build",
                 "--ssid", "lab"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert shlex.split(lines[0]) == ["arduino-cli", "upload", "--fqbn", EXPECTED_FQBN, "--port", "/dev/ttyUSB0",
                                     "--input-dir", str(REPO / "build" / "arduino-cli"),
                                     str(REPO / "firmware" / "cubecam")]
    assert lines[1].endswith("(password from stdin or a prompt)")
    assert len(lines) == 2


def test_dry_run_on_a_machine_without_either_tool_prints_the_one_install_command(tmp_path):
    env = {"PATH": "/usr/bin:/bin"}  # no arduino-cli; --pio hides the venv's own pio
    done = run_cubecam("flash", "--port", "/dev/ttyUSB0", "--dry-run", *no_pio(tmp_path), env=env)
    assert_one_line_error(done.returncode, done.stderr, "neither arduino-cli nor PlatformIO (pio) is installed")
    assert done.stdout == ""  # no plan naming tools that are not there
    command = shlex.split(done.stderr.split("`")[1])
    assert command == [sys.executable, "-m", "pip", "install", "platformio==6.2.0"]
    check = subprocess.run([*command[:4], "--dry-run", *command[4:]], check=False, capture_output=True, text=True,
                           timeout=300)
    assert check.returncode == 0 and "platformio" in check.stdout.lower()  # a command pip takes as it is


def test_the_flash_extra_pins_platformio_and_dry_run_then_builds_the_platformio_command_line(monkeypatch, capsys):
    import tomllib
    from importlib import metadata

    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert extras["flash"] == ["platformio==6.2.0"] and "cubetrack[flash]" in extras["test"]
    assert 'platformio==6.2.0; extra == "flash"' in metadata.requires("cubetrack")  # the installed metadata
    pio = Path(sys.executable).parent / "pio"  # where `pip install 'cubetrack[flash]'` put it
    version = subprocess.run([str(pio), "--version"], check=False, capture_output=True, text=True, timeout=120)
    assert version.stdout.strip().endswith("version 6.2.0")
    monkeypatch.setenv("PATH", "/usr/bin:/bin")  # no arduino-cli
    assert main(["flash", "--port", "/dev/ttyUSB0", "--dry-run"]) == 0
    lines = capsys.readouterr().out.splitlines()
    plan = [shlex.split(line) for line in lines[lines.index("# platformio") + 1:]]
    build = [str(pio), "run", "-d", str(REPO), "-e", "spresense"]
    assert plan == [build, [*build, "-t", "upload", "--upload-port", "/dev/ttyUSB0"]]


def test_all_without_boards(monkeypatch, capsys):
    monkeypatch.setattr(boards, "attached_boards", list)
    rc = main(["flash", "--all", "--dry-run"])
    assert_one_line_error(rc, capsys.readouterr().err, "no boards attached")


def test_name_refused_for_several_boards(monkeypatch, capsys):
    monkeypatch.setattr(boards, "attached_boards", lambda: [boards.Board("/dev/ttyUSB0", "a", ""),
                                                            boards.Board("/dev/ttyUSB1", "b", "")])
    rc = main(["flash", "--all", "--dry-run", "--name", "cam1"])
    assert_one_line_error(rc, capsys.readouterr().err, "--name cannot name 2 boards")


# --- the real PlatformIO and the real board package files ---


@pytest.mark.skipif(not Path(PIO).exists(), reason="PlatformIO is not installed in this environment")
def test_real_pio_without_the_spresense_platform(tmp_path):
    project = tmp_path / "fw"
    project.mkdir()
    (project / "platformio.ini").write_text(
        "[env:spresense]\nplatform = https://github.com/maxgerhardt/platform-sonyspresense.git\n"
        "board = spresense\nframework = arduino\n")
    done = run_cubecam("flash", "--port", "/dev/ttyUSB0", "--builder", "platformio", "--project", str(project),
                       "--pio", PIO, timeout=90,
                       env={"PLATFORMIO_CORE_DIR": str(tmp_path / "pio-core"),
                            "PLATFORMIO_SETTING_ENABLE_TELEMETRY": "No",
                            "PLATFORMIO_SETTING_CHECK_PLATFORMIO_INTERVAL": "9999"})
    assert_one_line_error(done.returncode, done.stderr, "Spresense platform for PlatformIO is not installed",
                          "pio pkg install")


@pytest.mark.skipif(not Path(PIO).exists(), reason="PlatformIO is not installed in this environment")
def test_real_pio_without_a_project(tmp_path, capsys):
    rc = main(["flash", "--port", "/dev/ttyUSB0", "--builder", "platformio", "--project", str(tmp_path),
               "--pio", PIO])
    assert_one_line_error(rc, capsys.readouterr().err, "platformio.ini: missing")


@pytest.mark.skipif(not Path(PIO).exists(), reason="PlatformIO is not installed in this environment")
def test_real_pio_with_the_repository_project_without_its_platform(tmp_path):
    done = run_cubecam("flash", "--port", "/dev/ttyUSB0", "--builder", "platformio", "--pio", PIO, timeout=90,
                       env={"PLATFORMIO_CORE_DIR": str(tmp_path / "pio-core"),
                            "PLATFORMIO_SETTING_ENABLE_TELEMETRY": "No"})
    assert_one_line_error(done.returncode, done.stderr, "platform-sonyspresense.git#", str(REPO / "platformio.ini"),
                          f"`pio pkg install -d {REPO} -e spresense`")


@pytest.mark.skipif(not Path(PIO).exists(), reason="PlatformIO is not installed in this environment")
def test_platformio_ini_pins_every_package():
    env = dict(os.environ, PLATFORMIO_SETTING_ENABLE_TELEMETRY="No")
    done = subprocess.run([PIO, "project", "config", "--json-output"], cwd=REPO, capture_output=True, text=True,
                          timeout=120, env=env, check=False)
    assert done.returncode == 0, done.stderr
    opts = dict(dict(json.loads(done.stdout))["env:spresense"])

    def pinned(spec: str) -> str:
        url, _, ref = spec.partition("#")
        assert len(ref) == 40 and all(c in "0123456789abcdef" for c in ref), spec
        return url

    assert pinned(opts["platform"]) == "https://github.com/maxgerhardt/platform-sonyspresense.git"
    packages = {name.strip(): pinned(url.strip())
                for name, _, url in (p.partition("@") for p in opts["platform_packages"])}
    assert set(packages) == {"framework-arduinosonyspresense", "tool-arduinosonyspresensesdk", "tool-spresense"}
    assert [pinned(dep) for dep in opts["lib_deps"]] == ["https://github.com/TomonobuHayakawa/GS2200-WiFi.git"]
    assert opts["lib_deps"][0].endswith("#6126fb4f885e33aa6fe5399996493cf8ed21fe92")
    assert int(opts["board_upload.speed"]) == 921600
    assert int(opts["board_upload.maximum_size"]) == int(opts["board_upload.maximum_ram_size"]) == 1536 * 1024


@pytest.mark.skipif(not (VENDOR_CORE / "boards.txt").exists(),
                    reason="Sony's board package sources are not in ../shared/vendor/spresense")
def test_fqbn_options_exist_in_the_real_boards_txt():
    boards_txt = configparser.ConfigParser(interpolation=None, delimiters=("=",))
    boards_txt.optionxform = str
    boards_txt.read_string("[b]\n" + (VENDOR_CORE / "boards.txt").read_text(encoding="utf-8"))
    props = boards_txt["b"]
    board, _, options = EXPECTED_FQBN.removeprefix("SPRESENSE:spresense:").partition(":")
    assert board in {key.split(".")[0] for key in props}
    for option in options.split(","):
        menu, _, value = option.partition("=")
        assert f"menu.{menu}" in props, menu
        assert f"{board}.menu.{menu}.{value}" in props, option
    assert props[f"{board}.menu.Memory.1536.upload.maximum_size"] == str(1536 * 1024)
    assert props[f"{board}.menu.UploadSpeed.921600.upload.speed"] == "-b 921600"
    assert props[f"{board}.vid.0"] == "0x10C4" and props[f"{board}.pid.0"] == "0xEA60"
