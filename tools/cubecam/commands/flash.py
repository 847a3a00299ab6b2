"""Build the firmware with PlatformIO, upload it to one or all attached boards, then provision
each board (when --ssid is given; options as for `cubecam provision`).

  cubecam flash --port /dev/ttyUSB0 --ssid lab --password-file ~/.lab-wifi --name cam1
  cubecam flash --all --dry-run

The commands run are `pio run -d <project> -e spresense` once, then
`pio run -d <project> -e spresense -t upload --upload-port <DEV>` per board; --dry-run
prints them (and the provisioning step) without running anything. PlatformIO and its
Spresense platform (which it downloads on first use) must be installed; both are checked
first. With --all and more than one board, --name is not allowed (each node keeps its own).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time

from cubecam.commands.provision import add_provision_options

HELP = "build and upload the firmware with PlatformIO, then provision"


def add_arguments(p: argparse.ArgumentParser) -> None:
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", metavar="DEV", help="the board's serial device, e.g. /dev/ttyUSB0")
    where.add_argument("--all", action="store_true", help="every attached board (USB 10C4:EA60)")
    p.add_argument("--dry-run", action="store_true", help="print the commands instead of running them")
    p.add_argument("--project", metavar="DIR", help="PlatformIO project folder (default: the repository root)")
    p.add_argument("--env", default="spresense", help="PlatformIO environment (default spresense)")
    p.add_argument("--pio", metavar="PATH", help="the pio executable (default: pio on PATH or beside this Python)")
    p.add_argument("--no-build", action="store_true", help="upload what was built before")
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


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from cubecam.boards import attached_boards
    from cubecam.errors import FlashError
    from cubecam.flash import (build_command, check_pio, check_platform, default_project, find_pio,
                               read_project, run_command, upload_command)

    if args.all:
        ports = [b.device for b in attached_boards()]
        if not ports:
            raise FlashError("--all: no boards attached (looked for USB 10C4:EA60); plug one in or give --port")
    else:
        ports = [args.port]
    if args.name and len(ports) > 1:
        raise FlashError(f"--name cannot name {len(ports)} boards at once; flash them one by one with --port")
    project_dir = Path(args.project) if args.project else default_project()
    req = None
    if args.ssid is not None and not args.dry_run:
        from cubecam.commands.provision import request_from_args

        req = request_from_args(args)  # ask for the password before the long build
    if args.dry_run:
        pio = find_pio(args.pio) or "pio"
        if not args.no_build:
            print(shlex.join(build_command(pio, project_dir, args.env)))
        for port in ports:
            print(shlex.join(upload_command(pio, project_dir, port, args.env)))
            if args.ssid is not None:
                print(_provision_text(args, port))
        return 0
    pio = check_pio(find_pio(args.pio))
    project = read_project(project_dir, args.env)
    check_platform(project)
    if not args.no_build:
        run_command(build_command(pio, project.path, project.env), "build")
    for port in ports:
        run_command(upload_command(pio, project.path, port, project.env), f"upload to {port}")
    if req is None:
        return 0
    from cubecam.commands.provision import provision_port

    time.sleep(1.0)  # the board reboots after the upload
    for port in ports:
        provision_port(port, req, args.config)
    print(f"cubecam flash: {len(ports)} board(s) flashed and provisioned", file=sys.stderr)
    return 0
