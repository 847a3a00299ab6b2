"""Build the firmware, upload it to one or all attached boards, then provision each board
(when --ssid is given; options as for `cubecam provision`).

  cubecam flash --port /dev/ttyUSB0 --ssid lab --password-file ~/.lab-wifi --name cam1
  cubecam flash --all --burn-bootloader --ssid lab --password-file ~/.lab-wifi
  cubecam flash --all --dry-run

Builders (--builder, default auto): arduino-cli with Sony's board package SPRESENSE:spresense
(chosen when `arduino-cli core list` shows it) builds the sketch folder firmware/cubecam for
SPRESENSE:spresense:spresense:Core=Main,Memory=1536,UploadSpeed=921600,Debug=Disabled; else
PlatformIO builds the repository's platformio.ini (environment spresense). The firmware is built
once, then uploaded board by board; --burn-bootloader first installs Sony's bootloader on each
board (needed once per board and board-package version). Before anything runs, the tool, the
board package, the GS2200-WiFi library and the bootloader files (or the PlatformIO platform) are
checked; a missing one stops with the commands that install it. --dry-run prints the commands
of both builders (or of --builder) and runs nothing; with neither tool installed it prints the one
command that installs PlatformIO at the pinned version (as `pip install 'cubetrack[flash]'` does).
A board that fails does not stop the others; each is reported, and the exit status is 1 when any
failed. With several boards, --name is
refused (each node keeps its own).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time

from cubecam.commands.provision import add_provision_options

HELP = "build and upload the firmware (arduino-cli or PlatformIO), then provision"


def add_arguments(p: argparse.ArgumentParser) -> None:
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", metavar="DEV", help="the board's serial device, e.g. /dev/ttyUSB0")
    where.add_argument("--all", action="store_true", help="every attached board (USB 10C4:EA60)")
    p.add_argument("--builder", choices=("auto", "arduino-cli", "platformio"), default="auto",
                   help="arduino-cli with Sony's board package, or PlatformIO (default auto: arduino-cli "
                        "when its board package SPRESENSE:spresense is installed)")
    p.add_argument("--dry-run", action="store_true", help="print the commands instead of running them")
    p.add_argument("--no-build", action="store_true", help="upload what was built before")
    p.add_argument("--burn-bootloader", action="store_true",
                   help="install Sony's bootloader on each board before uploading (once per board)")
    p.add_argument("--no-bootloader-check", action="store_true",
                   help="arduino-cli: do not require the bootloader files on this machine "
                        "(the boards got their bootloader elsewhere)")
    p.add_argument("--arduino-cli", metavar="PATH", help="the arduino-cli executable (default: on PATH)")
    p.add_argument("--sketch", metavar="DIR", help="arduino-cli: the sketch folder (default firmware/cubecam)")
    p.add_argument("--build-path", metavar="DIR", help="arduino-cli: the build folder (default build/arduino-cli)")
    p.add_argument("--pio", metavar="PATH", help="the pio executable (default: pio on PATH or beside this Python)")
    p.add_argument("--project", metavar="DIR", help="PlatformIO project folder (default: the repository root)")
    p.add_argument("--env", default="spresense", help="PlatformIO environment (default spresense)")
    add_provision_options(p, ssid_required=False)


def _provision_text(args: argparse.Namespace, port: str) -> str:
    cmd = ["cubecam", "provision", "--port", port, "--ssid", args.ssid]
    if args.open:
        cmd.append("--open")
    elif args.password_file:
        cmd += ["--password-file", args.password_file]
    for opt, value in (("--name", args.name), ("--quality", args.quality), ("--fps", args.fps),
                       ("--mode", args.mode), ("--ip", args.ip), ("--config", args.config)):
        if value is not None:
            cmd += [opt, f"{value:g}" if isinstance(value, float) else str(value)]
    if args.reboot:
        cmd.append("--reboot")
    text = shlex.join(cmd)
    if not args.open and not args.password_file:
        text += "   (password from stdin or a prompt)"
    return text


def _builder(name: str, args: argparse.Namespace, cli: str | None, pio: str | None):
    from pathlib import Path

    from cubecam.flash import ArduinoCli, PlatformIO, default_build_path, default_project, default_sketch

    if name == ArduinoCli.name:
        return ArduinoCli(cli or "arduino-cli", Path(args.sketch) if args.sketch else default_sketch(),
                          Path(args.build_path) if args.build_path else default_build_path())
    return PlatformIO(pio or "pio", Path(args.project) if args.project else default_project(), args.env)


def _print_plan(builder, args: argparse.Namespace, ports: list[str]) -> None:
    if not args.no_build:
        print(shlex.join(builder.build()))
    for port in ports:
        if args.burn_bootloader:
            print(shlex.join(builder.burn_bootloader(port)))
        print(shlex.join(builder.upload(port)))
    if args.ssid is not None:
        for port in ports:
            print(_provision_text(args, port))


def _check(builder, args: argparse.Namespace, ports: list[str], cli: str | None, pio: str | None) -> None:
    """What the chosen builder needs, found tool first."""
    from cubecam.flash import (
        ArduinoCli,
        check_arduino_cli,
        check_pio,
        check_platform,
        missing_arduino_cli,
        read_project,
    )

    if isinstance(builder, ArduinoCli):
        if cli is None:
            raise missing_arduino_cli()
        check_arduino_cli(builder, ports, args.burn_bootloader, not args.no_bootloader_check)
    else:
        check_pio(pio)
        check_platform(read_project(builder.project, builder.env))


def _say(text: str) -> None:
    print(f"cubecam flash: {text}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from cubecam.boards import attached_boards
    from cubecam.errors import CubecamError, FlashError
    from cubecam.flash import BUILDERS, choose_builder, find_tool, no_builder, run_command

    if args.all:
        ports = [b.device for b in attached_boards()]
        if not ports:
            raise FlashError("--all: no boards attached (looked for USB 10C4:EA60); plug one in or give --port")
    else:
        ports = [args.port]
    if args.name and len(ports) > 1:
        raise FlashError(f"--name cannot name {len(ports)} boards at once; flash them one by one with --port")
    cli = find_tool("arduino-cli", args.arduino_cli)
    pio = find_tool("pio", args.pio)
    if args.dry_run:
        if args.builder == "auto" and cli is None and pio is None:
            raise no_builder()  # the plan would name tools this machine does not have
        names = BUILDERS if args.builder == "auto" else (args.builder,)
        for name in names:
            if len(names) > 1:
                print(f"# {name}")
            _print_plan(_builder(name, args, cli, pio), args, ports)
        return 0
    name, why = choose_builder(args.builder, cli, pio)
    builder = _builder(name, args, cli, pio)
    _check(builder, args, ports, cli, pio)
    _say(f"building with {name} ({why})")
    req = None
    if args.ssid is not None:
        from cubecam.commands.provision import request_from_args

        req = request_from_args(args)  # ask for the password before the long build
    if not args.no_build:
        run_command(builder.build(), "build")
    failed: dict[str, str] = {}
    for port in ports:
        try:
            if args.burn_bootloader:
                run_command(builder.burn_bootloader(port), f"bootloader on {port}")
            run_command(builder.upload(port), f"upload to {port}")
        except FlashError as exc:
            failed[port] = str(exc)
            _say(f"{port}: FAILED: {exc}")
        else:
            _say(f"{port}: flashed")
    if req is not None:
        from cubecam.commands.provision import provision_port

        time.sleep(1.0)  # the boards reboot after the upload
        for port in [p for p in ports if p not in failed]:
            try:
                provision_port(port, req, args.config)
            except CubecamError as exc:
                failed[port] = f"provisioning failed: {exc}"
                _say(f"{port}: FAILED: {failed[port]}")
    if failed:
        raise FlashError(f"{len(failed)} of {len(ports)} board(s) failed: "
                         + "; ".join(f"{port}: {why}" for port, why in failed.items()))
    _say(f"{len(ports)} board(s) flashed" + (" and provisioned" if req is not None else ""))
    return 0
