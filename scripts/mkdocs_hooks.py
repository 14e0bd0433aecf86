"""MkDocs hooks: pages generated at build time from the code itself, so they cannot go stale.

- ``reference/cli.md`` from the ``occufly`` argument parser (every command, every option;
  the app's commands come in through the same entry point the CLI uses);
- ``reference/api.md`` from the app's OpenAPI schema, with the role each route needs
  (``app.access.table()``), made in a subprocess by ``create_app`` on a scratch data dir;
- ``bench/index.md`` from the benchmark JSON files in ``docs/bench/`` (newest run of each
  benchmark first; the lab-notebook history lives in ``bench/history.md``).

Nothing here reaches the network. Listed in ``mkdocs.yml`` under ``hooks:``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from mkdocs.structure.files import File

REPO = Path(__file__).resolve().parent.parent


# ---- CLI ------------------------------------------------------------------------------------
def _md_escape(text: str) -> str:
    return (text or "").replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;").replace(
        "\n", " ")


def _arg_rows(p: argparse.ArgumentParser) -> list[str]:
    rows = []
    for a in p._actions:  # noqa: SLF001 - argparse has no public walk of its actions
        if isinstance(a, (argparse._HelpAction, argparse._SubParsersAction)):  # noqa: SLF001
            continue
        name = ", ".join(a.option_strings) if a.option_strings else (a.metavar or a.dest)
        if a.option_strings and a.nargs != 0:
            name += " " + str(a.metavar or a.dest.upper())
        extra = []
        if a.choices:
            extra.append("one of " + ", ".join(f"`{c}`" for c in a.choices))
        if a.default not in (None, False, argparse.SUPPRESS) and a.nargs != 0:
            extra.append(f"default `{a.default}`")
        if a.required and a.option_strings:
            extra.append("required")
        help_text = "" if a.help == argparse.SUPPRESS else (a.help or "")
        if "%(" in help_text:
            try:
                help_text = help_text % {**vars(a), "prog": p.prog}
            except (KeyError, TypeError, ValueError):
                pass
        desc = "; ".join([t for t in [help_text] + extra if t])
        rows.append(f"| `{_md_escape(name)}` | {_md_escape(desc)} |")
    return rows


def _walk(p: argparse.ArgumentParser, prog: str, out: list[str], level: int = 2) -> None:
    subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]  # noqa: SLF001
    for sp in subs:
        helps = {ca.dest: ca.help for ca in sp._choices_actions}  # noqa: SLF001
        for name, child in sp.choices.items():
            full = f"{prog} {name}"
            out.append(f"{'#' * level} `{full}`\n")
            if helps.get(name):
                out.append(_md_escape(helps[name]) + "\n")
            if child.description:
                out.append(child.description.strip() + "\n")
            usage = child.format_usage().replace("usage: ", "").strip()
            out.append(f"```\n{usage}\n```\n")
            rows = _arg_rows(child)
            if rows:
                out.append("| argument | meaning |\n|---|---|\n" + "\n".join(rows) + "\n")
            _walk(child, full, out, level + 1)


def cli_reference() -> str:
    from occufly.cli import build_parser

    parser = build_parser()
    out = ["# CLI reference\n",
           "Generated from the `occufly` argument parser at documentation build time "
           "(`scripts/mkdocs_hooks.py`). Every command that reports something takes `--json`; "
           "errors a user can cause print one line naming the file and what was expected and "
           "exit with status 2; a command that finds nothing to do exits 2 too.\n",
           "| global option | meaning |\n|---|---|\n" + "\n".join(_arg_rows(parser)) + "\n"]
    _walk(parser, "occufly", out)
    return "\n".join(out)


# ---- REST API -------------------------------------------------------------------------------
_OPENAPI_SCRIPT = r"""
import json, os, sys, tempfile
d = tempfile.mkdtemp(prefix="occufly-docs-")
os.environ.update(OCCUFLY_DATA_DIR=d, OCCUFLY_ENV="development", OCCUFLY_LIFTING="off")
from app.access import table
from app.main import close, create_app
app = create_app()
try:
    json.dump({"openapi": app.openapi(), "access": table()}, sys.stdout)
finally:
    close(app)
"""


def openapi_and_access() -> tuple[dict, dict]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("OCCUFLY_")}
    r = subprocess.run([sys.executable, "-c", _OPENAPI_SCRIPT], capture_output=True, text=True,
                       cwd=REPO, env=env, timeout=300)
    if r.returncode != 0:
        raise RuntimeError(f"generating the OpenAPI schema failed:\n{r.stderr[-3000:]}")
    d = json.loads(r.stdout)
    return d["openapi"], d["access"]


def _schema_name(s: dict | None) -> str:
    if not s:
        return ""
    if "$ref" in s:
        return s["$ref"].rsplit("/", 1)[-1]
    if s.get("type") == "array":
        return f"list of {_schema_name(s.get('items'))}"
    return s.get("type", "") or ", ".join(_schema_name(x) for x in s.get("anyOf", []))


def api_reference() -> str:
    spec, access = openapi_and_access()
    levels = {
        "public": "anyone", "user": "any logged-in user",
        "member": "members of the scene (admins: all)",
        "annotator": "annotators of the scene, admins", "reviewer": "reviewers of the scene, admins",
        "staff": "reviewers and admins", "admin": "admins",
    }
    by_tag: dict[str, list[str]] = {}
    for path, ops in sorted(spec.get("paths", {}).items()):
        for method, op in ops.items():
            if method not in ("get", "post", "put", "patch", "delete"):
                continue
            key = f"{method.upper()} {path}"
            tag = (op.get("tags") or ["other"])[0]
            lines = [f"### `{key}`\n"]
            desc = (op.get("description") or "").strip()
            first = desc.split("\n\n")[0] if desc else op.get("summary", "")
            if first:
                lines.append(_md_escape(first) + "\n")
            lines.append(f"Who: {levels.get(access.get(key, ''), access.get(key, '?'))}.\n")
            params = op.get("parameters") or []
            if params:
                lines.append("| parameter | in | type | required |\n|---|---|---|---|")
                for prm in params:
                    lines.append(f"| `{prm['name']}` | {prm['in']} | "
                                 f"{_schema_name(prm.get('schema'))} | "
                                 f"{'yes' if prm.get('required') else 'no'} |")
                lines.append("")
            body = (op.get("requestBody") or {}).get("content") or {}
            for ctype, c in body.items():
                lines.append(f"Body: `{ctype}` {_schema_name(c.get('schema'))}\n")
            resp = []
            for code, r in sorted((op.get("responses") or {}).items()):
                content = r.get("content") or {}
                what = ", ".join(f"`{ct}` {_schema_name(c.get('schema'))}".strip()
                                 for ct, c in content.items())
                resp.append(f"{code} {what}".strip())
            if resp:
                lines.append("Responses: " + "; ".join(resp) + "\n")
            by_tag.setdefault(tag, []).append("\n".join(lines))
    out = ["# REST API reference\n",
           f"Generated from the app's OpenAPI schema ({spec['info']['title']} "
           f"{spec['info']['version']}) at documentation build time; a running app serves the "
           "same schema at `/openapi.json` and an interactive view at `/docs`. "
           "Auth: the session cookie `occufly_session` (browser; writes need the CSRF header) or "
           "`Authorization: Bearer <token>` from `POST /api/auth/login`. Errors are "
           "`{\"detail\": \"...\"}` with a 4xx status naming the field or file.\n"]
    for tag in sorted(by_tag):
        out.append(f"## {tag}\n")
        out.extend(by_tag[tag])
    names = sorted((spec.get("components") or {}).get("schemas", {}))
    if names:
        out.append("## Schemas\n")
        out.append("Request and response bodies (fields and types in `/openapi.json`): "
                   + ", ".join(f"`{n}`" for n in names) + ".\n")
    return "\n".join(out)


# ---- benchmarks -----------------------------------------------------------------------------
def _flat(d: object, prefix: str = "", out: dict | None = None, depth: int = 0) -> dict:
    out = {} if out is None else out
    if isinstance(d, dict) and depth < 3:
        for k, v in d.items():
            _flat(v, f"{prefix}.{k}" if prefix else str(k), out, depth + 1)
    elif isinstance(d, (int, float, str, bool)) or d is None:
        out[prefix] = d
    return out


def _fmt(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return _md_escape(str(v))


def bench_pages(bench_dir: Path) -> str:
    files = sorted(bench_dir.glob("*.json"), key=lambda p: p.name, reverse=True)
    groups: dict[str, list[Path]] = {}
    for p in files:
        stem = p.stem
        name = stem.split("_20")[0] if "_20" in stem else stem  # <bench>_<date>...
        groups.setdefault(name, []).append(p)
    out = ["# Benchmarks\n",
           "Current figures first: for each benchmark, its newest run (a JSON file in "
           "`docs/bench/`, printed by a script in `bench/`), generated at documentation build "
           "time. Timings on shared 2-core machines drift; the benchmarks report ratios "
           "against a baseline measured in the same run. Earlier runs are listed below each; "
           "the lab notebook of how the figures came about is [the history](history.md).\n"]
    for name, paths in sorted(groups.items()):
        newest = paths[0]
        try:
            data = json.loads(newest.read_text())
        except (OSError, ValueError) as e:
            out.append(f"## {name}\n\n`{newest.name}`: unreadable ({e})\n")
            continue
        flat = _flat(data)
        out.append(f"## {name}\n")
        out.append(f"Newest run: `{newest.name}`.\n")
        rows = [(k, v) for k, v in flat.items() if k][:60]
        if rows:
            out.append("| figure | value |\n|---|---|\n" + "\n".join(
                f"| `{_md_escape(k)}` | {_fmt(v)} |" for k, v in rows) + "\n")
        if len(flat) > 60:
            out.append(f"({len(flat) - 60} more figures in the file.)\n")
        if len(paths) > 1:
            out.append("Earlier runs: " + ", ".join(f"`{p.name}`" for p in paths[1:]) + ".\n")
    return "\n".join(out)


# ---- hook -----------------------------------------------------------------------------------
def on_files(files, config):  # noqa: ANN001, ANN201 - the MkDocs hook signature
    docs_dir = Path(config["docs_dir"])
    generated = {
        "reference/cli.md": cli_reference,
        "reference/api.md": api_reference,
        "bench/index.md": lambda: bench_pages(docs_dir / "bench"),
    }
    for uri, make in generated.items():
        existing = files.get_file_from_path(uri)
        if existing is not None:
            files.remove(existing)
        files.append(File.generated(config, uri, content=make()))
    return files


if __name__ == "__main__":  # print one generated page: python scripts/mkdocs_hooks.py cli|api|bench
    which = sys.argv[1] if len(sys.argv) > 1 else "cli"
    print({"cli": cli_reference, "api": api_reference,
           "bench": lambda: bench_pages(REPO / "docs" / "bench")}[which]())
