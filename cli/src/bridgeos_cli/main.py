"""The `bridgeos` root command: command groups are imported only when they run, so --help starts fast."""

from __future__ import annotations

import importlib

import click

from . import __version__

# name -> (module:attribute, one-line help shown by `bridgeos --help` without importing the module)
COMMANDS: dict[str, tuple[str, str]] = {
    "login": ("auth:login", "Log in to a cloud and keep its API token."),
    "logout": ("auth:logout", "Forget the stored login."),
    "whoami": ("auth:whoami", "Show the cloud and user this command line acts for."),
    "robots": ("robots:robots", "List and inspect robots."),
    "skills": ("skills:skills", "List, add, remove, start and stop a robot's Skills."),
    "components": ("skills:components", "Inspect, start, stop and migrate components."),
    "logs": ("logs:logs", "Print (and follow) the logs of a robot, Skill or component."),
    "events": ("events:events", "Print (and follow) the event log."),
    "recordings": ("recordings:recordings", "List and download a robot's MCAP recordings."),
    "metrics": ("metrics:metrics", "Query metrics, aggregated per time bucket."),
    "images": ("registry:images", "List the registry's repositories and tags."),
    "releases": ("rollouts:releases", "List, inspect and make Skill releases."),
    "rollouts": ("rollouts:rollouts", "Roll a release out to robots; pause, resume, abort."),
    "completion": ("main:completion", "Print the shell completion script (bash, zsh, fish)."),
}

EPILOG = """\b
Examples:
  bridgeos login https://cloud.example.com
  bridgeos robots ls
  bridgeos logs -f r1/people-detection/detector --level warning
  bridgeos robots ls --json | jq '.[].id'

\b
Exit codes: 0 ok, 1 the API refused the request, 2 bad command line,
3 not logged in or credentials refused, 4 not found, 5 cloud unreachable.
"""


class LazyGroup(click.Group):
    """A group whose subcommands live in modules imported on first use."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS:
            return None
        target, _ = COMMANDS[cmd_name]
        module_name, attribute = target.split(":")
        if module_name == "main":
            return globals()[attribute]
        module = importlib.import_module(f"bridgeos_cli.commands.{module_name}")
        command: click.Command = getattr(module, attribute)
        return command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        # The stored one-liners: listing the commands imports none of them.
        with formatter.section("Commands"):
            formatter.write_dl([(name, summary) for name, (_, summary) in COMMANDS.items()])


@click.group(cls=LazyGroup, epilog=EPILOG, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="bridgeos")
def cli() -> None:
    """bridgeos: drive a bridgeOS cloud from a shell or a CI job.

    Log in once with `bridgeos login URL`; the URL and an API token are kept in
    $XDG_CONFIG_HOME/bridgeos/config.json (mode 600). BRIDGEOS_URL and
    BRIDGEOS_TOKEN override them. Every listing takes --json for scripts.
    """


@click.command()
@click.argument("shell", type=click.Choice(["bash", "zsh", "fish"]))
def completion(shell: str) -> None:
    """Print the completion script of SHELL.

    \b
    Examples:
      bridgeos completion bash > ~/.local/share/bash-completion/completions/bridgeos
      echo 'eval "$(bridgeos completion zsh)"' >> ~/.zshrc
      bridgeos completion fish > ~/.config/fish/completions/bridgeos.fish
    """
    from click.shell_completion import get_completion_class

    completer = get_completion_class(shell)
    assert completer is not None  # every choice above has one
    click.echo(completer(cli, {}, "bridgeos", "_BRIDGEOS_COMPLETE").source())


def main() -> None:
    """Run the command line (the `bridgeos` console script)."""
    cli(prog_name="bridgeos")
