"""A user's mistake on the command line: one line that names what is wrong, a non-zero exit, no traceback."""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

import pytest

from iorthand.config import ConfigError, cli_number, read_yaml
from iorthand.transport import check_endpoint
from tests.conftest import ROOT, iorthand_cmd


def test_numbers_on_the_command_line_are_checked_like_settings() -> None:
    seconds = cli_number(float, lo=0.1, hi=600.0)
    assert seconds("2.5") == 2.5
    for text, why in (("0", "not within 0.1..600"), ("nan", "not within"), ("abc", "not a number")):
        with pytest.raises(argparse.ArgumentTypeError, match=why):
            seconds(text)
    with pytest.raises(argparse.ArgumentTypeError, match="not a whole number"):
        cli_number(int, lo=1)("1.5")


def test_endpoints_need_a_protocol_a_host_and_a_port() -> None:
    for good in ("tcp/127.0.0.1:7447", "tls/router.example.org:7447", "tcp/[::1]:7447", "tcp/0.0.0.0:7447#iface=eth0"):
        check_endpoint(good)
    for bad, why in (("nonsense", "must look like"), ("tcp/127.0.0.1:notaport", "'notaport' is not a port"),
                     ("tcp/127.0.0.1:99999", "'99999' is not a port"), ("tcp/:7447", "must look like")):
        with pytest.raises(ValueError, match=why):
            check_endpoint(bad)


def test_a_file_that_is_not_text_is_named(tmp_path: Path) -> None:
    path = tmp_path / "binary.yaml"
    path.write_bytes(b"\xff\xfe\x00bin")
    with pytest.raises(ConfigError, match=r"binary\.yaml: <top level>: not UTF-8 text"):
        read_yaml(path)


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(iorthand_cmd(*args), capture_output=True, text=True, timeout=60, cwd=cwd,
                          stdin=subprocess.DEVNULL)


@pytest.mark.parametrize(("args", "code", "said"), [
    (["certs", "show", "nosuch.pem"], 1, "nosuch.pem: cannot read"),
    (["certs", "password", "a:b", "--dir", "."], 1, "certificate name 'a:b' is not a role"),
    (["certs", "init", "--dir", "ca", "--days", "0"], 2, "--days: '0' is not within 1..inf"),
    (["report", "nosuchsession"], 1, "nosuchsession is not a recorded session: it has no manifest.json"),
    (["replay", "nosuchsession"], 1, "nosuchsession is not a recorded session"),  # before connecting (no router)
    (["operator", "--connect", "nonsense", "stop"], 2, "endpoint 'nonsense' must look like tcp/HOST:PORT"),
    (["router", "--listen", "tcp/127.0.0.1:notaport"], 2, "'notaport' is not a port number"),
    (["check", "--config", "binary.yaml"], 2, "not UTF-8 text"),
    (["bench", "transports", "--duration", "0"], 2, "--duration: '0' is not within 1..inf"),
    (["bench", "wan", "--profiles", "nosuch"], 2, "invalid choice: 'nosuch'"),
    (["export", "nosuchsession", "--start", "10", "--end", "5"], 2, "--end: 5 s is not after --start 10 s"),
    (["calibrate", "render", "board", "--dictionary", "NOSUCH"], 2, "unknown ArUco dictionary 'NOSUCH'"),
    (["calibrate", "render", "board", "--squares", "0", "0"], 2, "squares_x: expected at least 3, got 0"),
    (["twin", "--config", str(ROOT / "configs" / "twin.yaml"), "--bind", "0.0.0.0"], 2,
     "bind 0.0.0.0 is reachable from other machines, and the rerun viewer has no log-in"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_mistakes_are_answered_in_one_line(tmp_path: Path, args: list[str], code: int, said: str) -> None:
    (tmp_path / "binary.yaml").write_bytes(b"\xff\xfe\x00bin")
    r = _run(*args, cwd=tmp_path)
    assert (r.returncode, "Traceback" in r.stderr + r.stdout) == (code, False), r.stderr
    assert said in r.stderr + r.stdout
    assert not (tmp_path / "a:b.password").exists()  # a refused name writes nothing
    assert not (tmp_path / "ca").exists() and not (tmp_path / "board").exists()


def test_a_mistyped_option_names_the_subcommand_and_the_option_it_meant(tmp_path: Path) -> None:
    """Found by a review: ``iorthand demo --veiw`` printed the top-level usage and "unrecognized arguments", as if
    the mistake were in ``iorthand``; the subcommand's parser now answers for it, with its usage."""
    r = _run("demo", "--veiw", cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.splitlines()[-1] == "iorthand demo: unrecognized option --veiw (did you mean --view?)", r.stderr
    assert r.stderr.startswith("usage: iorthand demo "), r.stderr
    assert not list(tmp_path.iterdir())  # nothing started, nothing written


def _leaf_commands(parser: argparse.ArgumentParser, path: list[str]) -> list[tuple[list[str], argparse.ArgumentParser]]:
    """Every command line that ends in a parser of its own: leaves, and parents whose action may be left out."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [(path, parser)]
    out = [leaf for name, p in subs[0].choices.items() for leaf in _leaf_commands(p, [*path, name])]
    return out if subs[0].required else [(path, parser), *out]


def test_every_subcommand_answers_for_an_option_it_does_not_know(capsys: pytest.CaptureFixture[str]) -> None:
    """Each subcommand (nested ones too) names itself and the unknown option, and suggests the nearest of its own;
    its required arguments are given, so that the unknown option is the only mistake."""
    from iorthand.cli import build_parser

    fillers = {"listen": "127.0.0.1:1", "connect": "127.0.0.1:1"}  # bench linkemu checks HOST:PORT
    checked = 0
    for path, parser in _leaf_commands(build_parser(), []):
        if path == ["ur-emulator"]:
            continue  # every argument goes unparsed to the emulator's own parser (python -m iorthand_edge.ur_emulator)
        given = [a for a in parser._actions if a.required and not isinstance(a, argparse._SubParsersAction)]
        given += [g._group_actions[0] for g in parser._mutually_exclusive_groups if g.required]
        required: list[str] = []
        for a in given:
            value = [] if a.nargs == 0 else [fillers.get(a.dest, "x")]
            required += [a.option_strings[0], *value] if a.option_strings else value
        known = next(o for o in parser._option_string_actions if o != "--help" and o.startswith("--"))
        typo = known[:2] + known[3] + known[2] + known[4:]  # two letters swapped, as a hurried hand does
        with pytest.raises(SystemExit) as exit_:
            build_parser().parse_args([*path, typo, *required])
        said = capsys.readouterr().err.splitlines()[-1]
        assert exit_.value.code == 2, (path, said)
        assert said.startswith(f"iorthand {' '.join(path)}: unrecognized option {typo} (did you mean --"), said
        checked += 1
    assert checked >= 30
