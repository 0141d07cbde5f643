"""Command-line entry point of the bridgeOS robot agent."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO
from urllib.parse import urlsplit

import pydantic

from bridgeos_agent import __version__
from bridgeos_agent.errors import field_errors
from bridgeos_agent.labels import LabelError, parse_labels
from bridgeos_agent.robotconfig import parse_robot_config, robot_config_json_schema
from bridgeos_agent.ros2graph import Ros2Graph, rclpy_missing
from bridgeos_agent.skillconfig import parse_skill_config, skill_config_json_schema
from bridgeos_agent.tls import InsecureMaster, check_master_url
from bridgeos_agent.tokenfile import TokenFileError, read_token_file

__all__ = ["build_parser", "main"]

EXIT_OK = 0
EXIT_INVALID = 1
EXIT_USAGE = 2

MAX_ID_LENGTH = 128


def _master_url(value: str) -> str:
    """Accept a ws:// or wss:// URL with a host and, if given, a valid port."""
    value = value.strip()
    try:
        parts = urlsplit(value)
        port = parts.port
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"invalid master URL {value!r}: {exc}") from None
    if parts.scheme not in ("ws", "wss"):
        raise argparse.ArgumentTypeError(f"invalid master URL {value!r}: expected ws://HOST:PORT or wss://HOST:PORT")
    if not parts.hostname:
        raise argparse.ArgumentTypeError(f"invalid master URL {value!r}: missing host")
    if port == 0:
        raise argparse.ArgumentTypeError(f"invalid master URL {value!r}: port 0")
    if parts.query or parts.fragment:
        raise argparse.ArgumentTypeError(f"invalid master URL {value!r}: no query or fragment allowed")
    return value


def _identifier(what: str) -> Any:
    """Build an argparse type accepting a non-empty printable id without whitespace."""

    def check(value: str) -> str:
        if not value:
            raise argparse.ArgumentTypeError(f"{what} must not be empty")
        if len(value) > MAX_ID_LENGTH:
            raise argparse.ArgumentTypeError(f"{what} is longer than {MAX_ID_LENGTH} characters")
        if any(ch.isspace() or not ch.isprintable() for ch in value):
            raise argparse.ArgumentTypeError(f"{what} must not contain whitespace")
        return value

    return check


def _positive(option: str, *, zero: bool = False) -> Any:
    """Build an argparse type accepting a positive finite number (or zero too, with ``zero``)."""
    wanted = "zero or a positive number" if zero else "a positive number"

    def check(value: str) -> float:
        try:
            number = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{option} must be a number, not {value!r}") from None
        if not ((number >= 0 if zero else number > 0) and number < float("inf")):
            raise argparse.ArgumentTypeError(f"{option} must be {wanted}, not {value!r}")
        return number

    return check


def _metrics_address(value: str) -> str:
    """Accept HOST:PORT for --metrics."""
    from bridgeos_agent.metrics import parse_address

    try:
        parse_address(value)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--metrics {exc}") from None
    return value


def _door_address(option: str, usual: int) -> Callable[[str], str]:
    """Return the check of HOST:PORT for a bridge door (a port of its own: 0 is refused)."""

    def check(value: str) -> str:
        from bridgeos_agent.metrics import parse_address

        try:
            host, port = parse_address(value)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"{option} {exc}") from None
        if port == 0:
            raise argparse.ArgumentTypeError(f"{option} {value!r}: give a port (the usual one is {usual})")
        if any(ch.isspace() for ch in host):
            raise argparse.ArgumentTypeError(f"{option} {value!r}: the host must not contain whitespace")
        return value

    return check


_rosbridge_address = _door_address("--rosbridge", 9090)
_foxglove_address = _door_address("--foxglove", 8765)


def _device(value: str) -> str:
    """Accept a network device name (at most 15 letters, digits, '-', '_' or '.')."""
    if not value or len(value) > 15 or not all(ch.isalnum() or ch in "-_." for ch in value):
        raise argparse.ArgumentTypeError(f"invalid device name {value!r}: up to 15 letters, digits, '-', '_', '.'")
    return value


def build_parser() -> argparse.ArgumentParser:
    """Build the argument parser for every subcommand."""
    parser = argparse.ArgumentParser(
        prog="bridgeos-agent",
        description="bridgeOS robot agent: attach this robot to a bridgeOS cloud.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")

    commands.add_parser("version", help="print the agent's version")

    schema = commands.add_parser("schema", help="print the JSON Schema of a configuration")
    schema.add_argument("kind", choices=("skill", "robot"), help="which configuration")

    validate = commands.add_parser("validate", help="validate a configuration file")
    validate.add_argument("file", type=Path, help="JSON configuration file")
    validate.add_argument(
        "--kind",
        choices=("skill", "robot"),
        default="skill",
        help="configuration kind (default: skill)",
    )

    connection = argparse.ArgumentParser(add_help=False)
    connection.add_argument(
        "--master",
        type=_master_url,
        default=os.environ.get("BRIDGEOS_MASTER"),
        metavar="ws://HOST:PORT",
        help="cloud WebSocket URL (env BRIDGEOS_MASTER)",
    )
    connection.add_argument(
        "--robot",
        type=_identifier("robot id"),
        default=os.environ.get("BRIDGEOS_ROBOT"),
        metavar="ID",
        help="robot id (env BRIDGEOS_ROBOT)",
    )
    connection.add_argument(
        "--token",
        type=_identifier("token"),
        default=os.environ.get("BRIDGEOS_TOKEN"),
        metavar="TOKEN",
        help="robot token (env BRIDGEOS_TOKEN)",
    )
    connection.add_argument(
        "--token-file",
        type=Path,
        default=os.environ.get("BRIDGEOS_TOKEN_FILE") or None,
        metavar="PATH",
        help="file holding the robot token, read when --token is absent; when the cloud re-keys the robot, "
        "the new token replaces it there (mode 600) (env BRIDGEOS_TOKEN_FILE)",
    )
    connection.add_argument(
        "--runtime",
        choices=("docker", "process"),
        default=os.environ.get("BRIDGEOS_RUNTIME", "process"),
        help="how components are started (env BRIDGEOS_RUNTIME; default: process)",
    )

    connection.add_argument(
        "--ca",
        type=Path,
        default=os.environ.get("BRIDGEOS_CA") or None,
        metavar="FILE",
        help="CA certificate (PEM) that signs the cloud's TLS certificate (env BRIDGEOS_CA; default: the CA the "
        "cloud pinned in the robot config, else the system's CAs)",
    )
    connection.add_argument(
        "--allow-insecure",
        action="store_true",
        default=os.environ.get("BRIDGEOS_ALLOW_INSECURE", "") not in ("", "0", "false", "no"),
        help="allow plain ws:// to another machine: the token travels unencrypted (env BRIDGEOS_ALLOW_INSECURE=1)",
    )
    connection.add_argument(
        "--vpn-device",
        type=_device,
        default=os.environ.get("BRIDGEOS_VPN_DEVICE", "bridgeos-vpn"),
        metavar="NAME",
        help="name of the VPN tunnel device (env BRIDGEOS_VPN_DEVICE; default bridgeos-vpn)",
    )

    run = commands.add_parser(
        "run",
        parents=[connection],
        help="run the Robot Controller",
        description="Connect this robot to a bridgeOS cloud and run its Skills.",
    )
    run.add_argument(
        "--data-dir",
        type=Path,
        default=os.environ.get("BRIDGEOS_DATA_DIR"),
        help="where the agent keeps its state (env BRIDGEOS_DATA_DIR; default: ~/.local/share/bridgeos-agent/ROBOT)",
    )
    run.add_argument(
        "--simulate",
        action="store_true",
        default=os.environ.get("BRIDGEOS_SIMULATE", "") not in ("", "0", "false", "no"),
        help="run as a simulated robot with synthetic resources (env BRIDGEOS_SIMULATE=1)",
    )
    run.add_argument(
        "--ros2",
        choices=("auto", "on", "off"),
        default=os.environ.get("BRIDGEOS_ROS2", "auto"),
        help="run ROS 2 routing in the graph of this process's ROS_DOMAIN_ID and discovery settings; auto: when "
        "rclpy is installed and the robot is not simulated (env BRIDGEOS_ROS2)",
    )
    run.add_argument(
        "--sim-cpu", type=_positive("--sim-cpu"), default=2.0, metavar="CORES", help="simulated CPU cores (default 2)"
    )
    run.add_argument(
        "--sim-ram",
        type=_positive("--sim-ram"),
        default=2048.0,
        metavar="MIB",
        help="simulated memory in MiB (default 2048)",
    )
    run.add_argument(
        "--sim-bandwidth",
        type=_positive("--sim-bandwidth"),
        default=100.0,
        metavar="MBIT",
        help="simulated peak bandwidth in Mbit/s (default 100); it swings down to --sim-bandwidth-min and back",
    )
    run.add_argument(
        "--sim-bandwidth-min",
        type=_positive("--sim-bandwidth-min"),
        default=None,
        metavar="MBIT",
        help="the simulated bandwidth's low point in Mbit/s, at most the peak (default 5%% of the peak)",
    )
    run.add_argument(
        "--sample-interval",
        type=_positive("--sample-interval"),
        default=1.0,
        metavar="S",
        help="seconds between resource samples (default 1)",
    )
    run.add_argument(
        "--report-interval",
        type=_positive("--report-interval", zero=True),
        default=0.0,
        metavar="S",
        help="seconds between metrics frames to the cloud; the samples taken meanwhile travel in one frame "
        "(default 0: each sample in its own frame; a fleet of thousands sets 5)",
    )
    run.add_argument(
        "--outbox-memory",
        type=_positive("--outbox-memory"),
        default=os.environ.get("BRIDGEOS_OUTBOX_MEMORY", "8"),
        metavar="MIB",
        help="while the disk is full, keep up to this many MiB of metric frames in memory until the cloud has "
        "them; past it the oldest are dropped and counted (env BRIDGEOS_OUTBOX_MEMORY; default 8)",
    )
    run.add_argument(
        "--stop-components-on-exit",
        action="store_true",
        help="stop the robot's components when the agent stops (default: keep them for the next agent)",
    )
    run.add_argument(
        "--firewall",
        choices=("auto", "apply", "print", "off"),
        default=os.environ.get("BRIDGEOS_FIREWALL", "auto"),
        help="the robot's nftables rules: apply when root else print (auto, default), apply, print or off "
        "(env BRIDGEOS_FIREWALL)",
    )
    run.add_argument(
        "--metrics",
        type=_metrics_address,
        default=os.environ.get("BRIDGEOS_METRICS") or None,
        metavar="HOST:PORT",
        help="serve Prometheus metrics on http://HOST:PORT/metrics, unauthenticated: keep HOST on loopback "
        "or a monitoring network (env BRIDGEOS_METRICS)",
    )
    run.add_argument(
        "--rosbridge",
        type=_rosbridge_address,
        default=os.environ.get("BRIDGEOS_ROSBRIDGE") or None,
        metavar="HOST:PORT",
        help="serve the rosbridge v2 protocol for this robot's ROS graph on ws://HOST:PORT, unauthenticated "
        "like rosbridge_server: keep HOST on loopback, e.g. 127.0.0.1:9090 (env BRIDGEOS_ROSBRIDGE; default off)",
    )
    run.add_argument(
        "--rosbridge-ros",
        default=os.environ.get("BRIDGEOS_ROSBRIDGE_ROS", "auto"),
        help="which graph --rosbridge serves: ros1 (the ROS master of ROS_MASTER_URI), ros2 (this process's "
        "ROS 2 env) or auto: ros1 when a ROS master answers, else ros2 (env BRIDGEOS_ROSBRIDGE_ROS)",
    )
    run.add_argument(
        "--foxglove",
        type=_foxglove_address,
        default=os.environ.get("BRIDGEOS_FOXGLOVE") or None,
        metavar="HOST:PORT",
        help="serve the Foxglove WebSocket protocol for this robot's ROS graph on ws://HOST:PORT, unauthenticated "
        "like foxglove_bridge: keep HOST on loopback, e.g. 127.0.0.1:8765 (env BRIDGEOS_FOXGLOVE; default off)",
    )
    run.add_argument(
        "--foxglove-ros",
        default=os.environ.get("BRIDGEOS_FOXGLOVE_ROS", "auto"),
        help="which graph --foxglove serves: ros1, ros2 or auto, as for --rosbridge-ros (env BRIDGEOS_FOXGLOVE_ROS)",
    )
    run.add_argument(
        "--label",
        action="append",
        dest="label",
        metavar="KEY=VALUE",
        help="a label this robot registers with, repeatable (also k=v,k2=v2); the cloud applies them only while "
        "the robot has no labels yet, so an operator's later labels win (env BRIDGEOS_LABELS=k=v,k2=v2, used "
        "when no --label is given)",
    )
    run.add_argument("-q", "--quiet", action="store_true", help="print warnings and errors only")
    run.set_defaults(run_parser=run)

    doctor = commands.add_parser(
        "doctor",
        parents=[connection],
        help="check that this robot can run the agent",
        description="Check the cloud, the token, Docker, the ROS master and free resources; say how to fix what fails.",
    )
    doctor.set_defaults(run_parser=doctor)
    return parser


def _print_errors(errors: dict[str, list[str]], out: TextIO) -> None:
    """Print one line per field error."""
    for path, messages in errors.items():
        for message in messages:
            print(f"  {path}: {message}", file=out)


def _validate(path: Path, kind: str) -> int:
    """Validate one configuration file and report its field-level errors."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        print(f"bridgeos-agent validate: cannot read {path}: {exc.strerror}", file=sys.stderr)
        return EXIT_USAGE
    try:
        if kind == "skill":
            skill = parse_skill_config(data)
            summary = f"skill {skill.skill_id!r} with {len(skill.components)} component(s)"
        else:
            parse_robot_config(data)
            summary = "robot configuration"
    except pydantic.ValidationError as exc:
        errors = field_errors(exc)
        count = sum(len(messages) for messages in errors.values())
        print(f"{path}: invalid {kind} configuration ({count} error(s)):", file=sys.stderr)
        _print_errors(errors, sys.stderr)
        return EXIT_INVALID
    print(f"{path}: valid {summary}")
    return EXIT_OK


def _check_connection_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if not args.token and args.token_file is not None:
        try:
            args.token = read_token_file(args.token_file)
        except TokenFileError as exc:
            parser.error(f"--token-file {exc}")
    # argparse also applies each option's type to a string default, so values taken
    # from the environment are already checked; only absence is left to report.
    missing = [
        f"--{name} (or {env})"
        for name, env in (
            ("master", "BRIDGEOS_MASTER"),
            ("robot", "BRIDGEOS_ROBOT"),
            ("token", "BRIDGEOS_TOKEN"),
        )
        if not getattr(args, name)
    ]
    if missing:
        parser.error("missing " + ", ".join(missing))


def _check_simulation_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.sim_bandwidth_min is not None and args.sim_bandwidth_min > args.sim_bandwidth:
        parser.error(
            f"--sim-bandwidth-min {args.sim_bandwidth_min:g} is above the peak --sim-bandwidth {args.sim_bandwidth:g}"
        )


def _check_transport_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    try:
        check_master_url(args.master, allow_insecure=args.allow_insecure)
    except InsecureMaster as exc:
        parser.error(str(exc))
    if args.ca is not None and not args.ca.is_file():
        parser.error(f"--ca {args.ca}: no such file")


def _check_ros2_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    # argparse checks choices only on the command line, not on a default taken from the env.
    if args.ros2 not in ("auto", "on", "off"):
        parser.error(f"--ros2 (env BRIDGEOS_ROS2) must be auto, on or off, not {args.ros2!r}")
    if args.ros2 == "off":
        return
    try:
        Ros2Graph.from_env()
    except ValueError as exc:
        parser.error(f"the ROS 2 environment is not usable: {exc}")
    if args.ros2 == "on" and (missing := rclpy_missing()):
        parser.error(f"--ros2 on: {missing}")


def _check_rosbridge_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.rosbridge_ros not in ("auto", "ros1", "ros2"):
        parser.error(
            f"--rosbridge-ros (env BRIDGEOS_ROSBRIDGE_ROS) must be auto, ros1 or ros2, not {args.rosbridge_ros!r}"
        )
    if args.rosbridge is None:
        return
    try:
        import cbor2  # noqa: F401
    except ImportError:
        parser.error("--rosbridge needs cbor2: pip install 'bridgeos-agent[rosbridge]'")
    if args.rosbridge_ros == "ros1":
        try:
            import rosbags  # noqa: F401
        except ImportError:
            parser.error("--rosbridge-ros ros1 needs rosbags: pip install 'bridgeos-agent[rosbridge]'")
    if args.rosbridge_ros == "ros2" and (missing := rclpy_missing()):
        parser.error(f"--rosbridge-ros ros2: {missing}")


def _check_foxglove_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.foxglove_ros not in ("auto", "ros1", "ros2"):
        parser.error(
            f"--foxglove-ros (env BRIDGEOS_FOXGLOVE_ROS) must be auto, ros1 or ros2, not {args.foxglove_ros!r}"
        )
    if args.foxglove is None:
        return
    if args.foxglove == args.rosbridge:
        parser.error(f"--foxglove and --rosbridge cannot share {args.foxglove}")
    if args.foxglove_ros == "ros1":
        try:
            import rosbags  # noqa: F401
        except ImportError:
            parser.error("--foxglove-ros ros1 needs rosbags: pip install 'bridgeos-agent[rosbridge]'")
    if args.foxglove_ros == "ros2" and (missing := rclpy_missing()):
        parser.error(f"--foxglove-ros ros2: {missing}")


def _check_label_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    texts = args.label if args.label else [os.environ.get("BRIDGEOS_LABELS", "")]
    try:
        args.labels = parse_labels(texts)
    except LabelError as exc:
        parser.error(f"--label (env BRIDGEOS_LABELS): {exc}")


def _run(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """Check the run options, then run the Robot Controller until it is stopped."""
    _check_connection_args(parser, args)
    _check_label_args(parser, args)
    if args.data_dir is not None and args.data_dir.exists() and not args.data_dir.is_dir():
        parser.error(f"--data-dir {args.data_dir} exists and is not a directory")
    _check_transport_args(parser, args)
    _check_simulation_args(parser, args)
    _check_ros2_args(parser, args)
    _check_rosbridge_args(parser, args)
    _check_foxglove_args(parser, args)
    from bridgeos_agent.agent import run_agent

    return run_agent(args)


def _doctor(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """Check what the agent needs and print how to fix what is missing."""
    _check_connection_args(parser, args)
    _check_transport_args(parser, args)
    from bridgeos_agent.agent import doctor

    return doctor(args)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the bridgeos-agent command line and return its exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if args.command == "version":
            print(__version__)
            return EXIT_OK
        if args.command == "schema":
            schema = skill_config_json_schema() if args.kind == "skill" else robot_config_json_schema()
            print(json.dumps(schema, indent=2, sort_keys=False))
            return EXIT_OK
        if args.command == "validate":
            return _validate(args.file, args.kind)
        if args.command == "run":
            return _run(args.run_parser, args)
        if args.command == "doctor":
            return _doctor(args.run_parser, args)
    except SystemExit as exc:
        # argparse exits for --help and usage errors; return its code so main stays callable.
        return exc.code if isinstance(exc.code, int) else EXIT_USAGE
    except BrokenPipeError:
        # The reader (e.g. `| head`) went away; stop quietly instead of a traceback at exit.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_INVALID
    parser.print_help(sys.stderr)
    return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
