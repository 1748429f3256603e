"""``deploy/grafana-rayd.json``: every query names metrics the service exports and parses.

The metric list is the repository's ``proto/service.md`` ("Metrics"); the queries are
checked by ``promtool check rules`` (as recording rules, Grafana's variables replaced),
skipped with a message where promtool is not installed.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import pytest
from conftest import REPO

DASHBOARD = REPO / "deploy" / "grafana-rayd.json"


def _exported() -> set:
    table = (REPO / "proto" / "service.md").read_text().split("## Metrics", 1)[1]
    names = set()
    for line in table.splitlines():
        if not line.startswith("| `rayd_"):
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        kind = cells[1]
        for name in re.findall(r"`(rayd_[a-z_]+)`", cells[0]):
            names.add(name)
            if kind == "histogram":
                names.update({f"{name}_bucket", f"{name}_sum", f"{name}_count"})
    return names


def _queries():
    doc = json.loads(DASHBOARD.read_text())
    out = []
    for panel in doc["panels"]:
        for target in panel["targets"]:
            out.append((panel["title"], target["expr"]))
    return doc, out


def test_the_dashboard_shows_what_was_asked_for():
    doc, queries = _queries()
    titles = " ".join(p["title"] for p in doc["panels"]).lower()
    for wanted in ("queue", "latency", "mray/s", "cache"):
        assert wanted in titles
    assert len({p["id"] for p in doc["panels"]}) == len(doc["panels"])


def test_every_metric_in_the_dashboard_is_exported():
    exported = _exported()
    assert "rayd_jobs_queued" in exported and "rayd_job_duration_seconds_bucket" in exported
    _, queries = _queries()
    for title, expr in queries:
        for name in re.findall(r"\brayd_[a-z_]+", expr):
            assert name in exported, f"panel {title!r} uses {name}, which rayd does not export"


def test_every_query_parses(tmp_path):
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool is not installed (apt-get install prometheus)")
    _, queries = _queries()
    rules = ["groups:", "  - name: dashboard", "    rules:"]
    for i, (_, expr) in enumerate(queries):
        concrete = expr.replace("$__rate_interval", "5m").replace("$instance", ".*")
        rules += [f"      - record: dashboard:query{i}", f"        expr: {json.dumps(concrete)}"]
    path = tmp_path / "rules.yml"
    path.write_text("\n".join(rules) + "\n")
    done = subprocess.run([promtool, "check", "rules", str(path)], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
