"""Building and uploading the firmware with PlatformIO, to one or all attached boards.

The commands are exactly::

    pio run -d <project> -e spresense
    pio run -d <project> -e spresense -t upload --upload-port <DEV>      (per board)

The project is the repository root (its ``platformio.ini`` builds the sources in ``firmware/``).

PlatformIO must be installed (``pip install platformio``) and so must the Spresense platform
named in the project's ``platformio.ini`` (it is fetched from the internet on first use; a
machine without internet access needs it installed beforehand). Both are checked before
anything runs, offline: PlatformIO by running ``pio --version``, the platform by looking in
PlatformIO's core folder (``$PLATFORMIO_CORE_DIR``, default ``~/.platformio``).
"""

from __future__ import annotations

import configparser
import json
import os
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from cubecam.errors import FlashError

ENV = "spresense"
PLATFORM_NAME = "sonyspresense"
PLATFORM_URL = "https://github.com/maxgerhardt/platform-sonyspresense.git"
PIO_CHECK_TIMEOUT_S = 60.0


def default_project() -> Path:
    """The repository root, where ``platformio.ini`` is (next to ``tools/``)."""
    return Path(__file__).resolve().parents[2]


def find_pio(explicit: str | None = None) -> str | None:
    """The ``pio`` executable: explicit, else on PATH, else next to this Python."""
    if explicit:
        return explicit if Path(explicit).is_file() and os.access(explicit, os.X_OK) else None
    found = shutil.which("pio")
    if found:
        return found
    beside = Path(sys.executable).parent / "pio"
    return str(beside) if beside.is_file() else None


def build_command(pio: str, project: Path, env: str = ENV) -> list[str]:
    return [pio, "run", "-d", str(project), "-e", env]


def upload_command(pio: str, project: Path, port: str, env: str = ENV) -> list[str]:
    return [pio, "run", "-d", str(project), "-e", env, "-t", "upload", "--upload-port", port]


@dataclass(frozen=True, slots=True)
class Project:
    path: Path
    env: str
    platform: str  # the env's `platform =` value


def read_project(project: Path, env: str = ENV) -> Project:
    ini = project / "platformio.ini"
    parser = configparser.ConfigParser(interpolation=None)
    try:
        with ini.open(encoding="utf-8") as f:
            parser.read_file(f)
    except FileNotFoundError:
        raise FlashError(f"{ini}: missing; --project must be the firmware's PlatformIO project folder") from None
    except (OSError, configparser.Error) as exc:
        raise FlashError(f"{ini}: unreadable ({exc})") from None
    section = f"env:{env}"
    if not parser.has_section(section):
        envs = [s[4:] for s in parser.sections() if s.startswith("env:")]
        raise FlashError(f"{ini}: no [{section}] (has {', '.join(envs) or 'no environments'})")
    platform = parser.get(section, "platform", fallback="") or parser.get("env", "platform", fallback="")
    if not platform:
        raise FlashError(f"{ini}: [{section}] names no platform")
    return Project(project, env, platform.strip())


def core_dir() -> Path:
    return Path(os.environ.get("PLATFORMIO_CORE_DIR") or Path.home() / ".platformio")


def platform_installed(platform: str, project: Path, core: Path | None = None) -> bool:
    """Whether the platform named by ``platform`` (a name, a git URL, or symlink:// / file://
    path) is available without downloading anything."""
    for scheme in ("symlink://", "file://"):
        if platform.startswith(scheme):
            local = Path(platform[len(scheme):])
            local = local if local.is_absolute() else project / local
            return (local / "platform.json").is_file()
    wanted = platform.rstrip("/").rsplit("/", 1)[-1].removesuffix(".git").removeprefix("platform-")
    wanted = wanted.split("@", 1)[0].split("#", 1)[0]
    folder = (core or core_dir()) / "platforms"
    if not folder.is_dir():
        return False
    for meta in folder.glob("*/platform.json"):
        try:
            name = json.loads(meta.read_text(encoding="utf-8")).get("name", "")
        except (OSError, ValueError):
            continue
        if name in (wanted, PLATFORM_NAME):
            return True
    return False


def check_pio(pio: str | None) -> str:
    """A working ``pio``, or FlashError saying how to get one."""
    if pio is None:
        raise FlashError("PlatformIO (pio) not found: install it with `pip install platformio==6.2.0` "
                         "or give its path with --pio")
    try:
        done = subprocess.run([pio, "--version"], capture_output=True, text=True, timeout=PIO_CHECK_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise FlashError(f"PlatformIO at {pio} does not run ({exc})") from None
    if done.returncode != 0:
        raise FlashError(f"PlatformIO at {pio} does not run: `pio --version` exited {done.returncode}")
    return pio


def check_platform(project: Project) -> None:
    if not platform_installed(project.platform, project.path):
        raise FlashError(
            f"the Spresense platform for PlatformIO is not installed (platform = {project.platform} in "
            f"{project.path / 'platformio.ini'}; looked in {core_dir() / 'platforms'}): with internet access run "
            f"`pio pkg install -g -p {PLATFORM_URL}` (or `pio run -e {project.env}` once)")


def run_command(cmd: list[str], what: str) -> None:
    """Run a PlatformIO command with its output passed through; FlashError when it fails."""
    print(f"cubecam flash: {shlex.join(cmd)}", file=sys.stderr, flush=True)
    try:
        done = subprocess.run(cmd)
    except OSError as exc:
        raise FlashError(f"{what}: cannot run {cmd[0]} ({exc.strerror or exc})") from None
    if done.returncode != 0:
        raise FlashError(f"{what} failed: `{shlex.join(cmd)}` exited {done.returncode} (its output is above)")
