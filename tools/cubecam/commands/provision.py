"""Provision a camera node over USB serial: Wi-Fi credentials through Improv serial v1, other
settings through the node's line console (contracts §2).

The port is opened without toggling DTR/RTS (which would reset a Spresense); the tool waits
for the node by repeating Improv "current state" once a second. The Wi-Fi password is read
from --password-file, else from stdin when it is not a terminal, else from a prompt; it is
never taken from the command line and never printed. On success the node's name and URL are
printed; with --config the camera is added to (or updated in) a tracker config TOML.

  cubecam provision --port /dev/ttyUSB0 --ssid lab --password-file ~/.lab-wifi --name cam1
  echo "$PW" | cubecam provision --port /dev/ttyUSB0 --ssid lab --name cam2 --config tracker.toml
  cubecam provision --port /dev/ttyUSB0 --ssid cubecam-ap --mode ap --ip 192.168.50.1/24,192.168.50.1
"""

from __future__ import annotations

import argparse
import getpass
import sys

HELP = "send Wi-Fi and camera settings to a node over USB serial"


def add_provision_options(p: argparse.ArgumentParser, ssid_required: bool) -> None:
    """The options shared with `cubecam flash`."""
    p.add_argument("--ssid", required=ssid_required, help="Wi-Fi network name (in ap mode: the network the node opens)")
    p.add_argument("--password-file", metavar="F", help="file whose first line is the Wi-Fi password "
                                                        "(default: stdin if piped, else a prompt)")
    p.add_argument("--open", action="store_true", help="the network has no password (do not ask for one)")
    p.add_argument("--name", help="node name (letters, digits, _ and -), also its camera name in the config")
    p.add_argument("--quality", type=int, metavar="Q", help="JPEG quality 1..100")
    p.add_argument("--fps", type=float, metavar="F", help="frame rate (the node accepts 30, 15 or 7.5)")
    p.add_argument("--mode", choices=("station", "ap"), help="join a network (station) or open one (ap)")
    p.add_argument("--ip", metavar="dhcp|A.B.C.D/P,GW", help="dhcp, or a static address/prefix and gateway")
    p.add_argument("--config", metavar="CFG", help="tracker config TOML to add the camera to (created if missing)")
    p.add_argument("--boot-timeout", type=float, default=15.0, metavar="S",
                   help="wait this long for the node to answer (default 15)")
    p.add_argument("--join-timeout", type=float, default=45.0, metavar="S",
                   help="wait this long for it to join (default 45)")
    p.add_argument("--reboot", action="store_true", help="reboot the node afterwards and check it comes "
                                                         "back provisioned")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--port", required=True, metavar="DEV", help="the board's serial device, e.g. /dev/ttyUSB0")
    add_provision_options(p, ssid_required=True)
    p.add_argument("--scan", action="store_true", help="first list the Wi-Fi networks the node sees")


def request_from_args(args: argparse.Namespace):
    from cubecam.errors import ProvisionError
    from cubecam.provision import ProvisionRequest, read_password

    if args.open:
        if args.password_file:
            raise ProvisionError("--open and --password-file contradict each other")
        password = ""
    else:
        password = read_password(args.password_file, sys.stdin, getpass.getpass)
        if not password:
            raise ProvisionError("empty Wi-Fi password; use --open for a network without one")
    return ProvisionRequest(ssid=args.ssid, password=password, name=args.name, jpeg_quality=args.quality,
                            fps=args.fps, mode=args.mode, ip=args.ip, boot_timeout_s=args.boot_timeout,
                            join_timeout_s=args.join_timeout, reboot=args.reboot).check()


def provision_port(device: str, req, config: str | None, scan: bool = False) -> int:
    from cubecam.configfile import set_camera
    from cubecam.errors import ProvisionError
    from cubecam.link import NodeLink
    from cubecam.provision import provision

    def say(text: str) -> None:
        print(f"cubecam provision: {device}: {text}", file=sys.stderr, flush=True)

    with NodeLink.open(device) as node:
        if scan:
            node.wait_ready(req.boot_timeout_s)
            for net in node.scan():
                print(f"{net.ssid}\t{net.rssi} dBm\t{'secured' if net.secured else 'open'}", flush=True)
        result = provision(node, req, say)
    print(f"{result.name or '(unnamed)'} {result.url}", flush=True)
    if config:
        if not result.name:
            raise ProvisionError(f"{device}: the node has no name; give --name to add it to {config}")
        outcome = set_camera(config, result.name, result.stream_url)
        say(f"camera {result.name} {outcome} in {config}")
    return 0


def run(args: argparse.Namespace) -> int:
    req = request_from_args(args)
    return provision_port(args.port, req, args.config, args.scan)
