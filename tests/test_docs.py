"""The manual (docs/, mkdocs.yml): it builds with --strict, its generated references cover every
command, option, config key and bus key, and its examples run as written."""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
EXAMPLE = re.compile(r"^( *)<!-- example(?: cwd=(\w+))? -->\n\1```(\w+)\n(.*?)^\1```", re.S | re.M)


def examples() -> list[tuple[str, str, str]]:
    """(page, cwd, script) per page: its blocks marked ``<!-- example -->``, in order, joined."""
    out = []
    for page in sorted(DOCS.rglob("*.md")):
        blocks = [(m.group(2) or "root", "\n".join(line[len(m.group(1)):]
                                                   for line in m.group(4).splitlines()))
                  for m in EXAMPLE.finditer(page.read_text())]
        if blocks:
            assert len({cwd for cwd, _ in blocks}) == 1, f"{page}: one cwd per page"
            out.append((str(page.relative_to(DOCS)), blocks[0][0],
                        "\n".join(script for _, script in blocks)))
    return out


def _env() -> dict[str, str]:
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    for var in ("SCANCELL_CELL", "SCANCELL_CONNECT"):
        env.pop(var, None)
    return env


@pytest.mark.process
@pytest.mark.parametrize("page,cwd,script", examples(), ids=[e[0] for e in examples()])
def test_the_examples_run_as_written(tmp_path, page, cwd, script):
    work = ROOT if cwd == "root" else tmp_path
    path = tmp_path / "example.sh"
    path.write_text("set -e\n" + script)
    out = subprocess.run(["bash", str(path)], cwd=work, env=_env(), capture_output=True,
                         text=True, timeout=100)
    assert out.returncode == 0, f"{page}:\n{out.stdout}\n{out.stderr}"
    if page == "how-to/run-the-daemon.md":
        assert "scancell daemon --config deploy/cells/mock.toml &" in script
        assert re.search(r"^cell mock ", out.stdout, re.M), out.stdout
        assert re.search(r"^robot\s+robot\s+mock_robot\s+connected", out.stdout, re.M), out.stdout
        assert '"joints_deg"' in out.stdout and '"point_mm"' in out.stdout, out.stdout
        assert re.search(r"^mock_robot\s+scancell\.devices\.mock:MockRobot", out.stdout, re.M)
    if page == "tutorials/your-own-part.md":
        assert (tmp_path / "plan.toml").read_text().count("[[station]]") >= 3


def test_the_examples_are_found():
    pages = {page for page, _, _ in examples()}
    assert {"how-to/run-the-daemon.md", "how-to/tls.md", "tutorials/your-own-part.md"} <= pages


@pytest.mark.process
def test_the_site_builds_strictly_and_home_links_the_five_questions(tmp_path):
    site = tmp_path / "site"
    out = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(site)],
                         cwd=ROOT, env=dict(_env(), NO_MKDOCS_2_WARNING="1"), capture_output=True,
                         text=True, timeout=180)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "WARNING" not in out.stderr, out.stderr
    home = (site / "index.html").read_text()
    # one click from the home page, each a page of its own
    for page, must in (("reference/bus/fusion.html", "fusion/cloud"),
                       ("how-to/add-a-driver.html", "AcmeTracker"),
                       ("reference/config/scanner.html", "exposures_us"),
                       ("explanation/uncertainty-coverage.html", "95 % interval"),
                       ("how-to/tls.html", "certificate authority")):
        assert f'href="{page}"' in home, page
        assert must in (site / page).read_text(), page
    for picture in ("cell-layout", "data-flow", "frames", "job-stages"):
        assert (site / "pictures" / f"{picture}.svg").read_bytes().startswith(b"<?xml"), picture
    # a report page, made by an inspection as the site was built
    report = (site / "pictures" / "inspection" / "report.html").read_text()
    assert "<html" in report and "car_rear.step" in report
    assert (site / "pictures" / "inspection" / "map.png").read_bytes().startswith(b"\x89PNG")


def test_every_command_and_option_is_in_the_cli_reference():
    from scancell.cli import COMMANDS, build_parser
    from scancell.docsgen import cli_reference

    pages = cli_reference.pages()
    root = build_parser()
    seen = 0
    for top in cli_reference.walk_top(root):
        text = pages[f"reference/cli/{top.path[0]}.md"]
        for command in [top, *cli_reference.walk(top.parser, top.path)]:
            assert f"`scancell {' '.join(command.path)}`" in text or len(command.path) == 1
            for name in cli_reference.option_names(command.parser):
                assert f"`{name}`" in text, (command.path, name)
                seen += 1
    assert set(COMMANDS) == {t.path[0] for t in cli_reference.walk_top(root)}
    assert seen > 200


def _nest(table: str, key: str, value) -> dict:
    """``("metrology.scanner_check", "every", 1)`` -> a raw config with that key set."""
    path = table.split(".") + key.split(".")
    raw: dict = {"cell": {"name": "docs"}}
    node = raw
    for part in path[:-1]:
        node = node.setdefault(part, {})
    node[path[-1]] = value
    return raw


def _problem(raw: dict) -> str:
    from scancell.config import ConfigError, parse_cell_config

    try:
        parse_cell_config(raw, "docs.toml")
    except ConfigError as exc:
        return str(exc)
    return ""


UNKNOWN = re.compile(r"unknown (key|table|limit)|Additional properties")


def test_every_documented_config_key_is_one_the_parser_knows_and_no_other():
    from scancell.docsgen import config_reference

    tables = [t for t in config_reference.tables() if t.name != "devices.<name>"]
    assert {t.name for t in tables} >= {"cell", "bus", "daemon", "scanner", "recorder", "planner",
                                        "metrology", "inspection", "acceptance", "simulator"}
    for t in tables:
        assert t.keys, t.name
        for key in t.keys:
            problem = _problem(_nest(t.name, key, "zz-not-a-value"))
            assert not UNKNOWN.search(problem), (t.name, key, problem)
        # a key the page does not list is refused, so the page lists every key there is
        problem = _problem(_nest(t.name, "no_such_key_zz", 1))
        assert UNKNOWN.search(problem) and "no_such_key_zz" in problem, (t.name, problem)


def test_the_config_pages_hold_every_table_and_driver():
    from scancell.devices.registry import available_drivers
    from scancell.docsgen import config_reference

    pages = config_reference.pages()
    for t in config_reference.tables():
        page = pages[f"reference/config/{t.name.replace('.<name>', '').replace('.', '-')}.md"]
        for key, spec in t.keys.items():
            assert f"| `{key}` |" in page, (t.name, key)
            assert spec.unit in page
            assert spec.doc, f"[{t.name}] {key}: no description in the config model"
    drivers = pages["reference/config/drivers.md"]
    for name in available_drivers():
        assert f'driver = "{name}"' in drivers, name
    assert "| `timeout_s` | number (> 0) |  | s |" in drivers
    scanner = pages["reference/config/scanner.md"]
    assert "`exposures_us`" in scanner and "µs" in scanner


def _keys_of_cell_keys() -> list[str]:
    """Every key :class:`CellKeys` builds, with ``X`` for each argument, relative to the cell."""
    import inspect

    from scancell.protocols.keys import DEVICE_STREAMS, CellKeys

    keys = CellKeys("c")
    out = [keys.dev("X", stream) for stream, _, _ in DEVICE_STREAMS.values()]
    for name, member in inspect.getmembers(CellKeys):
        if name.startswith("_") or name in ("relative", "all", "prefix", "cell", "root", "dev"):
            continue
        if isinstance(member, property):
            out.append(getattr(keys, name))
        elif callable(member):
            n = len(inspect.signature(member).parameters) - 1
            out.append(getattr(keys, name)(*["X"] * n))
    return [keys.relative(k) for k in out]


def test_every_bus_key_and_message_is_in_the_bus_reference():
    from scancell.docsgen import bus_reference
    from scancell.protocols.keys import KEY_CATALOGUE
    from scancell.protocols.messages import json_schema_names

    patterns = [re.compile("^" + re.sub(r"<[^>]+>", "[^/]+", d.key) + "$") for d in KEY_CATALOGUE]
    built = _keys_of_cell_keys()
    assert len(built) > 25
    for key in built:
        assert any(p.match(key) for p in patterns), f"{key} is not in KEY_CATALOGUE"
    pages = bus_reference.pages()
    text = "\n".join(pages.values())
    for d in KEY_CATALOGUE:
        assert f"## `{d.key}`" in pages[f"reference/bus/{d.group}.md"], d.key
    for name in json_schema_names():
        if name.startswith("scancell.cmd."):
            verb = name.removeprefix("scancell.cmd.").split(".")
            assert verb[-1] in pages["reference/commands.md"], name
        else:
            assert f"reference/messages/{name}.md" in pages, name
            assert f"`{name}`" in text


def _driver_module() -> types.ModuleType:
    text = (DOCS / "how-to" / "add-a-driver.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    module = types.ModuleType("acme_tracker_from_the_docs")
    exec(compile(code, "add-a-driver.md", "exec"), module.__dict__)
    return module


@pytest.mark.process
def test_the_driver_how_to_measures_through_a_real_socket_and_names_each_fault():
    from scancell.devices.errors import BadReply, BeamBroken, ConnectionLost

    module = _driver_module()
    replies = iter([b"OK 3300.5 -2.25 100 0.01 0.01 0.012\n", b"OK 1\n", b"BEAM\n",
                    b"garbage\n"])

    async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while await reader.readline():
            reply = next(replies, None)
            if reply is None:
                break
            writer.write(reply)
            await writer.drain()
        writer.close()

    async def run() -> None:
        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        tracker = module.AcmeTracker("tracker", {"host": "127.0.0.1", "port": port})
        await tracker.connect()
        m = await tracker.measure()
        assert list(m.point_mm) == [3300.5, -2.25, 100.0] and m.sigma_mm[2] == 0.012
        assert (await tracker.status()).beam_locked is True
        with pytest.raises(BeamBroken):
            await tracker.measure()
        with pytest.raises(BadReply, match="garbage"):
            await tracker.measure()
        with pytest.raises(ConnectionLost, match="closed the link"):
            await tracker.measure()
        await tracker.close()
        server.close()
        await server.wait_closed()

    asyncio.run(run())
    import jsonschema

    jsonschema.Draft202012Validator.check_schema(module.AcmeTracker.OPTIONS_SCHEMA)
    assert {"measure", "status", "health"} <= set(module.AcmeTracker.operation_specs())
