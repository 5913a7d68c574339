"""The ``oibar`` configuration file: one TOML file for everything the command line takes.

Layout: one table per subcommand, named as on the command line (``[nav]``, ``[link]``,
``[pose]``, ``[replay]``, ``[calibrate-camera]``, ``[calib.estimate]``...); each key is a long
option without its dashes, with the value it would take there::

    verbose = 1                   # the top-level options (oibar -v)

    [nav]
    camera = "/dev/video0"
    port = "/dev/ttyACM0"
    rate-hz = 10.0
    calibration = "camera.yaml"   # relative paths: from this file's folder
    record-frames = true          # a switch: true or false
    live = true                   # an optional value: true is the option alone, else its
                                  # value: live = "127.0.0.1:8765"

Every value goes through the option's own argparse type (the same ranges and messages as on
the command line). The command line wins over the file; the file wins over the built-in
defaults. An option that takes several values (``link``'s ``command``) gets the command line's
values after the file's. Of two options that exclude each other (``calibrate-camera``'s
``--chessboard`` and ``--charuco``) the file may set one; when the command line gives the other,
the file's is dropped. An option whose value may be left out (``oibar nav --live [HOST:]PORT``)
takes ``true`` for the option alone, ``false`` for its absence, or its value
(``live = "127.0.0.1:8765"``, ``live = 8765``). A file that does not parse, an unknown table or
key, a value of the wrong kind or out of range is an error (exit status 2), never silently
ignored: a daemon under systemd must not fly on a default because of a typo.

Which file: ``--config FILE`` (before or after the subcommand), else $OIBAR_CONFIG, else the
first that exists of $XDG_CONFIG_HOME/oibar/oibar.toml (~/.config/oibar/oibar.toml when unset)
and /etc/oibar/oibar.toml. ``--config none`` (or OIBAR_CONFIG=none) reads no file.
"""

from __future__ import annotations

import argparse
import os
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

SYSTEM_CONFIG = Path("/etc/oibar/oibar.toml")
NO_CONFIG = "none"


class ConfigError(Exception):
    """The configuration file is missing, unreadable or invalid (exit status 2)."""


def user_config_path() -> Path:
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "oibar" / "oibar.toml"


def search_path() -> list[Path]:
    """Where a configuration is looked for when neither --config nor $OIBAR_CONFIG names one."""
    return [user_config_path(), SYSTEM_CONFIG]


def config_from_argv(argv: Sequence[str]) -> str | None:
    """The value of the last ``--config`` in ``argv`` (options after a bare ``--`` excluded)."""
    found = None
    it = iter(argv)
    for arg in it:
        if arg == "--":
            break
        if arg == "--config":
            found = next(it, None)
        elif arg.startswith("--config="):
            found = arg.split("=", 1)[1]
    return found


def find_config(argv: Sequence[str]) -> Path | None:
    """The configuration file this command line uses, or None. A file named explicitly (--config,
    $OIBAR_CONFIG) must exist; the default locations are used only when they do."""
    named = config_from_argv(argv)
    if named is None:
        named = os.environ.get("OIBAR_CONFIG") or None
    if named is not None:
        if named.strip().lower() == NO_CONFIG:
            return None
        path = Path(named).expanduser()
        if not path.is_file():
            raise ConfigError(f"{path}: no such file")
        return path
    return next((p for p in search_path() if p.is_file()), None)


def add_config_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        metavar="FILE",
        default=argparse.SUPPRESS,
        help="TOML configuration file (default: $OIBAR_CONFIG, else ~/.config/oibar/oibar.toml, "
        "else /etc/oibar/oibar.toml, when present; 'none': no file); the command line overrides it",
    )


def load(path: Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read it: {exc.strerror or exc}") from None


def apply(parser: argparse.ArgumentParser, path: Path) -> None:
    """Validate the whole file against ``parser`` and make its values the parser's defaults."""
    _apply_table(parser, load(path), path, [])


def subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """The settable options by key: the first long option string without its dashes."""
    out = {}
    for action in parser._actions:
        if not action.option_strings or action.dest in ("help", "version", "config"):
            continue
        if isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            continue
        out[_key(action)] = action
    return out


def _where(table: list[str], key: str | None = None) -> str:
    name = f"[{'.'.join(table)}]" if table else "top level"
    return f"{name} {key}" if key else name


def _apply_table(
    parser: argparse.ArgumentParser, table: dict[str, Any], path: Path, names: list[str]
) -> None:
    subs = subparsers(parser)
    options = _options(parser)
    positionals = {a.dest for a in parser._actions if not a.option_strings}
    defaults: dict[str, Any] = {}
    set_by_file: list[argparse.Action] = []
    for key, value in table.items():
        if key in subs:
            if not isinstance(value, dict):
                raise ConfigError(
                    f"{path}: {key!r} is a subcommand: make it a table, [{'.'.join(names + [key])}]"
                )
            _apply_table(subs[key], value, path, names + [key])
            continue
        action = options.get(key)
        if action is None:
            known = sorted(options) + [f"[{'.'.join(names + [s])}]" for s in sorted(subs)]
            hint = ""
            if key.replace("_", "-") in options:
                hint = f" (did you mean {key.replace('_', '-')!r}?)"
            elif key in positionals:
                hint = " (a positional argument: give it on the command line)"
            raise ConfigError(
                f"{path}: unknown key {key!r} in {_where(names)}{hint}; known: {', '.join(known) or 'none'}"
            )
        defaults[action.dest] = _value(action, value, path, _where(names, key), path.parent)
        action.required = False  # given by the file; the command line may still override it
        set_by_file.append(action)
    for group in parser._mutually_exclusive_groups:
        members = [a for a in set_by_file if a in group._group_actions]
        if members:
            group.required = False
            _command_line_wins(group, members, path, names)  # before set_defaults: the built-in defaults
    if defaults:
        parser.set_defaults(**defaults)


class _DropsFileValue(argparse.Action):
    """Mixed into an option of a mutually exclusive group whose other member the file sets:
    given on the command line, the option first puts that member back to its built-in default,
    as if the file had not set it (argparse itself checks only what the command line gives)."""

    dropped: tuple[str, Any] = ("", None)  # (dest, built-in default) of the member the file sets

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        setattr(namespace, *self.dropped)
        super().__call__(parser, namespace, values, option_string)


def _command_line_wins(group: Any, set_by_file: list[argparse.Action], path: Path, names: list[str]) -> None:
    """The file sets ``set_by_file`` of exclusive ``group``: one at most (the command line
    refuses two as well), whose value the group's other options drop when the command line
    gives them."""
    if len(set_by_file) > 1:
        keys = " and ".join(_key(a) for a in set_by_file)
        raise ConfigError(f"{path}: {_where(names)}: {keys} exclude each other: set one of them")
    given = set_by_file[0]
    for other in group._group_actions:
        if other is given:
            continue
        cls = type(other)
        if not issubclass(cls, _DropsFileValue):
            other.__class__ = type(cls.__name__, (_DropsFileValue, cls), {})
        other.dropped = (given.dest, given.default)  # type: ignore[attr-defined]


def _key(action: argparse.Action) -> str:
    longs = [s for s in action.option_strings if s.startswith("--")]
    return (longs or action.option_strings)[0].lstrip("-")


def _value(action: argparse.Action, value: Any, path: Path, where: str, base: Path) -> Any:
    """``value`` from the file, checked and converted by ``action``'s own rules."""
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
        if not isinstance(value, bool):
            raise ConfigError(f"{path}: {where} = {value!r}: must be true or false")
        # store_true keeps its switch's meaning: true sets it (the const), false leaves it off
        return action.const if value else not action.const
    if isinstance(action, argparse._CountAction):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ConfigError(f"{path}: {where} = {value!r}: must be an integer >= 0")
        return value
    if action.nargs == "?" and isinstance(value, bool):
        # an option whose value may be left out (`--live` alone): true is the option given bare
        return action.const if value else action.default
    if isinstance(action, (argparse._StoreConstAction, argparse._AppendConstAction)):
        raise ConfigError(f"{path}: {where}: this option cannot be set in the configuration file")
    many = action.nargs in ("+", "*") or isinstance(action, (argparse._AppendAction, argparse._ExtendAction))
    if many:
        items = value if isinstance(value, list) else None
        if items is None or (action.nargs == "+" and not items):
            raise ConfigError(f"{path}: {where} = {value!r}: must be a list of values")
        return [_scalar(action, item, path, where, base) for item in items]
    return _scalar(action, value, path, where, base)


def _scalar(action: argparse.Action, value: Any, path: Path, where: str, base: Path) -> Any:
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise ConfigError(f"{path}: {where} = {value!r}: must be a string or a number")
    text = value if isinstance(value, str) else repr(value)
    convert = action.type if callable(action.type) else str
    try:
        out = convert(text)
    except argparse.ArgumentTypeError as exc:
        raise ConfigError(f"{path}: {where} = {value!r}: {exc}") from None
    except (TypeError, ValueError):
        name = getattr(convert, "__name__", "value")
        raise ConfigError(f"{path}: {where} = {value!r}: not a valid {name}") from None
    if action.choices is not None and out not in action.choices:
        choices = ", ".join(map(repr, action.choices))
        raise ConfigError(f"{path}: {where} = {value!r}: must be one of {choices}")
    if isinstance(out, Path):
        out = out.expanduser()
        if not out.is_absolute():
            out = base / out  # relative to the file, not to the daemon's working folder
    return out
