"""MkDocs hooks (``mkdocs.yml`` ``hooks:``): the generated reference pages and pictures are added
to the site when it is built, so they are never stored and never drift from the code."""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent

#: the device protocols' documents, kept beside their codecs in ``protocols/``
PROTOCOL_DOCS = {"TRACKER_PROTOCOL.md": "tracker-line.md", "EMSCON.md": "emscon.md",
                 "DLP_HID_PROTOCOL.md": "dlp-hid.md"}


def generated_pages() -> dict[str, str | bytes]:
    """Every generated page and picture: site path -> content."""
    from scancell.docsgen import bus_reference, cli_reference, config_reference, example_report, pictures

    out: dict[str, str | bytes] = {}
    out.update(cli_reference.pages())
    out.update(config_reference.pages())
    out.update(bus_reference.pages())
    for src, dest in PROTOCOL_DOCS.items():
        out[f"reference/protocols/{dest}"] = (ROOT / "protocols" / src).read_text()
    out.update(pictures.pictures())
    out.update(example_report.example_report())
    return out


_pages: dict[str, str | bytes] = {}


def on_config(config):
    """Generate the pages once, and list the generated reference pages in the nav under their
    index page (``reference/cli/index.md`` gets every ``reference/cli/*.md``)."""
    _pages.clear()
    _pages.update(generated_pages())
    config["nav"] = [_expand(item) for item in config["nav"]]
    return config


def _expand(item):
    if isinstance(item, dict):
        return {title: _expand(value) for title, value in item.items()}
    if isinstance(item, list):
        return [_expand(v) for v in item]
    if isinstance(item, str) and item.endswith("/index.md") and item in _pages:
        folder = item.removesuffix("index.md")
        children = [{Path(p).stem: p} for p in _pages
                    if p.startswith(folder) and p != item and p.endswith(".md")
                    and "/" not in p.removeprefix(folder)]
        return [item, *children]
    return item


def on_files(files: Files, config) -> Files:
    for path, content in _pages.items():
        files.append(File.generated(config, path, content=content))
    return files
