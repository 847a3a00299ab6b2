"""Building and uploading the camera-node firmware to one or all attached boards, with
arduino-cli and Sony's board package, or with PlatformIO.

arduino-cli (Sony's supported path; the sketch folder is ``firmware/cubecam``)::

    arduino-cli compile --fqbn <FQBN> --build-path <BUILD> <SKETCH>
    arduino-cli upload --fqbn <FQBN> --port <DEV> --input-dir <BUILD> <SKETCH>        (per board)
    arduino-cli burn-bootloader --fqbn <FQBN> --port <DEV> --programmer sfutools     (once per board)

where ``<FQBN>`` is :data:`FQBN`: the board ``SPRESENSE:spresense:spresense`` with the menu
options of the board package's ``boards.txt`` (MainCore, 1536 KB of MainCore RAM, XMODEM at
921600 baud, no debug build). PlatformIO (``platformio.ini`` at the repository root)::

    pio run -d <PROJECT> -e spresense
    pio run -d <PROJECT> -e spresense -t upload --upload-port <DEV>                   (per board)
    pio run -d <PROJECT> -e spresense -t bootloader --upload-port <DEV>               (once per board)

Everything a build needs is checked before anything runs, and each missing piece (the tool,
Sony's board package, the GS2200-WiFi library, the bootloader files, the PlatformIO platform) is
one :class:`FlashError` naming the commands that install it. The checks only ask the tools what
is installed (``arduino-cli core list`` ...) and read files; nothing is downloaded.
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
from typing import ClassVar

from cubecam.errors import FlashError

QUERY_TIMEOUT_S = 60.0

# --- arduino-cli and Sony's board package ---

PACKAGE_INDEX_URL = ("https://github.com/sonydevworld/spresense-arduino-compatible/releases/download/"
                     "generic/package_spresense_index.json")
PLATFORM_ID = "SPRESENSE:spresense"
BOARD_ID = "SPRESENSE:spresense:spresense"
# boards.txt menus: the MainCore application; all 1536 KB of RAM for it (default 768 KB), since
# the three VGA JPEG camera buffers take up to 3 x 153.6 kB beside the application; XMODEM at
# 921600 baud (the default is 115200).
BOARD_OPTIONS = {"Core": "Main", "Memory": "1536", "UploadSpeed": "921600", "Debug": "Disabled"}
FQBN = BOARD_ID + ":" + ",".join(f"{menu}={value}" for menu, value in BOARD_OPTIONS.items())
BOOTLOADER_PROGRAMMER = "sfutools"  # programmers.txt: "Spresense Firmware Updater"
GS2200_LIBRARY = "GS2200"  # library.properties name of TomonobuHayakawa/GS2200-WiFi
GS2200_GIT_URL = "https://github.com/TomonobuHayakawa/GS2200-WiFi.git#6126fb4f885e33aa6fe5399996493cf8ed21fe92"
ARDUINO_CLI_INSTALL = ("mkdir -p ~/.local/bin && curl -fsSL "
                       "https://raw.githubusercontent.com/arduino/arduino-cli/master/install.sh | "
                       "BINDIR=~/.local/bin sh")

# --- PlatformIO ---

ENV = "spresense"
PLATFORM_NAME = "sonyspresense"
PLATFORM_URL = "https://github.com/maxgerhardt/platform-sonyspresense.git"


def platformio_requirement() -> str:
    """PlatformIO as the ``flash`` extra of the installed cubetrack pins it (pyproject.toml),
    e.g. ``platformio==6.2.0``; plain ``platformio`` when the package metadata is not there."""
    from importlib import metadata

    try:
        requires = metadata.requires("cubetrack") or []
    except metadata.PackageNotFoundError:
        requires = []
    for requirement in requires:
        spec, _, marker = requirement.partition(";")
        if spec.strip().startswith("platformio") and 'extra == "flash"' in marker:
            return spec.strip()
    return "platformio"


def pio_install_command() -> str:
    """The one command that installs PlatformIO where :func:`find_tool` finds it: beside the
    Python this tool runs on (the same as ``pip install 'cubetrack[flash]'`` in that environment)."""
    return f"{shlex.quote(sys.executable)} -m pip install {platformio_requirement()}"


def default_project() -> Path:
    """The repository root, where ``platformio.ini`` is (next to ``tools/``)."""
    return Path(__file__).resolve().parents[2]


def default_sketch() -> Path:
    return default_project() / "firmware" / "cubecam"


def default_build_path() -> Path:
    return default_project() / "build" / "arduino-cli"


@dataclass(frozen=True, slots=True)
class ArduinoCli:
    """The sketch folder built once into ``build_path`` and uploaded from there."""

    name: ClassVar[str] = "arduino-cli"
    exe: str
    sketch: Path
    build_path: Path

    def build(self) -> list[str]:
        return [self.exe, "compile", "--fqbn", FQBN, "--build-path", str(self.build_path), str(self.sketch)]

    def upload(self, port: str) -> list[str]:
        return [self.exe, "upload", "--fqbn", FQBN, "--port", port, "--input-dir", str(self.build_path),
                str(self.sketch)]

    def burn_bootloader(self, port: str) -> list[str]:
        return [self.exe, "burn-bootloader", "--fqbn", FQBN, "--port", port, "--programmer", BOOTLOADER_PROGRAMMER]


@dataclass(frozen=True, slots=True)
class PlatformIO:
    """An environment of a PlatformIO project."""

    name: ClassVar[str] = "platformio"
    exe: str
    project: Path
    env: str = ENV

    def build(self) -> list[str]:
        return [self.exe, "run", "-d", str(self.project), "-e", self.env]

    def upload(self, port: str) -> list[str]:
        return [*self.build(), "-t", "upload", "--upload-port", port]

    def burn_bootloader(self, port: str) -> list[str]:
        return [*self.build(), "-t", "bootloader", "--upload-port", port]


BUILDERS = (ArduinoCli.name, PlatformIO.name)


def find_tool(name: str, explicit: str | None = None) -> str | None:
    """An executable: ``explicit`` when it is one (None when not), else ``name`` on PATH, else
    next to this Python."""
    if explicit:
        return explicit if Path(explicit).is_file() and os.access(explicit, os.X_OK) else None
    found = shutil.which(name)
    if found:
        return found
    beside = Path(sys.executable).parent / name
    return str(beside) if beside.is_file() and os.access(beside, os.X_OK) else None


def query(cmd: list[str]) -> str:
    """The standard output of a quick, read-only tool command; FlashError when it fails."""
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=QUERY_TIMEOUT_S, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise FlashError(f"`{shlex.join(cmd)}` does not run ({exc})") from None
    if done.returncode != 0:
        said = done.stderr.strip().splitlines()
        raise FlashError(f"`{shlex.join(cmd)}` exited {done.returncode}" + (f": {said[-1]}" if said else ""))
    return done.stdout


def query_json(cmd: list[str]):
    out = query(cmd)
    try:
        return json.loads(out)
    except ValueError:
        raise FlashError(f"`{shlex.join(cmd)}` did not print JSON: {out.strip()[:80]!r}") from None


def _rows(data, key: str) -> list[dict]:
    """arduino-cli 1.x wraps JSON lists in an object (``{key: [...]}``, null when empty); 0.x
    prints the bare list."""
    rows = data.get(key) if isinstance(data, dict) else data
    return [row for row in rows or [] if isinstance(row, dict)]


def installed_platforms(cli: str) -> dict[str, str]:
    """Installed board packages (platform id -> version) according to ``arduino-cli core list``."""
    found = {}
    for row in _rows(query_json([cli, "core", "list", "--format", "json"]), "platforms"):
        # key names: 1.x id/installed_version, 0.18-0.35 id/installed, up to 0.17 ID/Installed
        pid = row.get("id") or row.get("ID")
        version = row.get("installed_version") or row.get("installed") or row.get("Installed")
        if pid and version:
            found[pid] = version
    return found


def installed_libraries(cli: str) -> dict[str, str]:
    """Installed libraries (name -> version) according to ``arduino-cli lib list``."""
    found = {}
    for row in _rows(query_json([cli, "lib", "list", "--format", "json"]), "installed_libraries"):
        library = row.get("library") or {}
        if library.get("name"):
            found[library["name"]] = library.get("version", "")
    return found


def sdk_firmware_dir(cli: str) -> Path | None:
    """Where the board package keeps the bootloader files (platform.txt:
    ``{runtime.tools.spresense-sdk.path}/spresense/firmware``), None when arduino-cli does not say."""
    data = query_json([cli, "board", "details", "--fqbn", BOARD_ID, "--show-properties=expanded", "--format", "json"])
    properties = data.get("build_properties", []) if isinstance(data, dict) else []
    for prop in properties:
        key, _, value = str(prop).partition("=")
        if key == "runtime.tools.spresense-sdk.path" and value:
            return Path(value) / "spresense" / "firmware"
    return None


@dataclass(frozen=True, slots=True)
class LoaderFiles:
    """The bootloader files of the board package on this machine: ``version.json`` names the
    loader the SDK needs and where to download it; ``stored_version.json`` appears once Sony's
    archive has been unpacked there (by the burn-bootloader licence dialog). Sony's SDK tools
    compare the two the same way to warn that a new loader is needed."""

    folder: Path
    required: str | None
    unpacked: str | None
    download_url: str

    @property
    def ready(self) -> bool:
        return self.required is None or self.required == self.unpacked

    @property
    def archive(self) -> Path:
        return self.folder / "firmware.zip"


def _loader_version(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as exc:
        raise FlashError(f"{path}: unreadable ({exc})") from None
    return data if isinstance(data, dict) else {}


def read_loader_files(folder: Path) -> LoaderFiles:
    wanted = _loader_version(folder / "version.json")
    return LoaderFiles(folder, wanted.get("LoaderVersion"),
                       _loader_version(folder / "stored_version.json").get("LoaderVersion"),
                       wanted.get("DownloadURL", ""))


def missing_arduino_cli() -> FlashError:
    return FlashError(f"arduino-cli not found: install it with `{ARDUINO_CLI_INSTALL}` "
                      f"(or give its path with --arduino-cli); or use --builder platformio")


def no_builder() -> FlashError:
    """Neither arduino-cli nor PlatformIO: the one command that fixes it (PlatformIO at the pinned version)."""
    return FlashError(f"neither arduino-cli nor PlatformIO (pio) is installed: run `{pio_install_command()}` "
                      f"(PlatformIO as cubetrack's flash extra pins it; arduino-cli instead: docs/hardware.md)")


def missing_board_package() -> FlashError:
    return FlashError(
        f"Sony's Spresense board package ({PLATFORM_ID}) is not installed for arduino-cli: run "
        f"`arduino-cli config add board_manager.additional_urls {PACKAGE_INDEX_URL}`, "
        f"`arduino-cli core update-index` and `arduino-cli core install {PLATFORM_ID}` "
        f"(run `arduino-cli config init` first if you have no arduino-cli.yaml)")


def choose_builder(requested: str, cli: str | None, pio: str | None) -> tuple[str, str]:
    """The builder to use, and why when it was detected: arduino-cli when Sony's board package
    is installed for it, else PlatformIO when installed."""
    if requested != "auto":
        return requested, f"--builder {requested}"
    if cli is not None:
        if PLATFORM_ID in installed_platforms(cli):
            return ArduinoCli.name, f"arduino-cli has Sony's board package {PLATFORM_ID}"
        if pio is None:
            raise missing_board_package()
        return PlatformIO.name, f"arduino-cli lacks Sony's board package {PLATFORM_ID}"
    if pio is None:
        raise no_builder()
    return PlatformIO.name, "arduino-cli not found"


def check_arduino_cli(builder: ArduinoCli, ports: list[str], burn_bootloader: bool, loader_check: bool) -> None:
    """The sketch, Sony's board package, the GS2200-WiFi library and (unless ``loader_check`` is
    off) the bootloader files, or FlashError with the commands that install the missing one."""
    cli = builder.exe
    ino = builder.sketch / f"{builder.sketch.name}.ino"
    if not ino.is_file():
        raise FlashError(f"{ino}: missing; --sketch must be the firmware's sketch folder (firmware/cubecam)")
    if PLATFORM_ID not in installed_platforms(cli):
        raise missing_board_package()
    if GS2200_LIBRARY not in installed_libraries(cli):
        raise FlashError(
            f"the GS2200-WiFi library ({GS2200_LIBRARY}) is not installed for arduino-cli: run "
            f"`arduino-cli config set library.enable_unsafe_install true` and "
            f"`arduino-cli lib install --git-url {GS2200_GIT_URL}`")
    folder = sdk_firmware_dir(cli) if loader_check else None
    loader = read_loader_files(folder) if folder is not None else None
    if loader is None or loader.ready or (burn_bootloader and loader.archive.is_file()):
        return
    port = ports[0] if len(ports) == 1 else "DEV"
    raise FlashError(
        f"Sony's Spresense bootloader {loader.required} has not been installed from this machine "
        f"({loader.folder / 'stored_version.json'} is {'for ' + loader.unpacked if loader.unpacked else 'missing'}): "
        f"download {loader.download_url or 'it from developer.sony.com'}, save it as {loader.archive}, then run "
        f"`{shlex.join(builder.burn_bootloader(port))}` once per board and accept Sony's licence in the window "
        f"it opens (or add --burn-bootloader; --no-bootloader-check if the boards already have it)")


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
    wanted = platform.split("#", 1)[0].rstrip("/").rsplit("/", 1)[-1].removesuffix(".git").removeprefix("platform-")
    wanted = wanted.split("@", 1)[0]
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
        raise FlashError(f"PlatformIO (pio) not found: install it with `{pio_install_command()}` "
                         "or give its path with --pio")
    query([pio, "--version"])
    return pio


def check_platform(project: Project) -> None:
    if not platform_installed(project.platform, project.path):
        raise FlashError(
            f"the Spresense platform for PlatformIO is not installed (platform = {project.platform} in "
            f"{project.path / 'platformio.ini'}; looked in {core_dir() / 'platforms'}): with internet access run "
            f"`pio pkg install -d {project.path} -e {project.env}`")


def run_command(cmd: list[str], what: str) -> None:
    """Run a build, upload or bootloader command with its output passed through; FlashError
    when it fails."""
    print(f"cubecam flash: {shlex.join(cmd)}", file=sys.stderr, flush=True)
    try:
        done = subprocess.run(cmd, check=False)
    except OSError as exc:
        raise FlashError(f"{what}: cannot run {cmd[0]} ({exc.strerror or exc})") from None
    if done.returncode != 0:
        raise FlashError(f"{what} failed: `{shlex.join(cmd)}` exited {done.returncode} (its output is above)")
