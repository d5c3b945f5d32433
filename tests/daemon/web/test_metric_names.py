"""``/metrics`` names as Prometheus' naming guide asks (the review's finding 14): a unit spelled out in the name
(``_degrees_per_hour``, not ``_dph``), counters in ``_total``; the ``_dph`` names kept for one release as
deprecated duplicates.  ``promtool check metrics`` judges the exposition and ``promtool check rules`` / ``check
config`` the shipped alert rules and scrape job where the binary is installed (Debian's ``prometheus``; CI
installs it); elsewhere the prometheus-client parser reads the exposition and the rules are read as YAML."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import yaml
from prometheus_client import CollectorRegistry, generate_latest
from web_helpers import SCRAPED_STATE, check_exposition

from fog_driver.daemon.web.metrics import DEPRECATED_NAMES, METRICS, DaemonCollector, LatencyHistogram

MONITORING = Path(__file__).resolve().parents[3] / "configs" / "monitoring"


def exposition(state: dict) -> str:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(DaemonCollector(lambda: state, LatencyHistogram()))
    return generate_latest(registry).decode()


def test_a_scrape_names_no_metric_in_dph_but_the_deprecated_duplicates():
    text = exposition(SCRAPED_STATE)
    families = check_exposition(text)
    samples = {s.name: s.value for f in families for s in f.samples if not s.labels}
    helps = {f.name: f.documentation for f in families}
    dph = {name for name in samples if name.endswith("_dph")}
    assert dph == set(DEPRECATED_NAMES)  # all five there (the state has each), and no other
    for old, new in DEPRECATED_NAMES.items():
        assert new.endswith("_degrees_per_hour") and new in METRICS and old not in METRICS
        assert samples[old] == samples[new]  # the same value under both names
        assert "deprecated" in helps[old] and new in helps[old], helps[old]
    assert not [name for name in METRICS if re.search(r"_dph\b", name)]
    # the figures under the new names, against the state's
    angle, status = SCRAPED_STATE["angle"], SCRAPED_STATE["status"]
    assert samples["fog_driver_drift_degrees_per_hour"] == angle["drift_dph"]
    assert samples["fog_driver_drift_sigma_degrees_per_hour"] == angle["drift_sigma_dph"]
    assert samples["fog_driver_rate_degrees_per_hour"] == SCRAPED_STATE["rate_1s_dph"]
    assert samples["fog_driver_bias_degrees_per_hour"] == status["bias_dph"]
    assert samples["fog_driver_bias_sigma_degrees_per_hour"] == status["bias_sigma_dph"]


def test_every_counter_ends_in_total_and_every_gauge_does_not():
    families = check_exposition(exposition(SCRAPED_STATE))
    for family in families:
        kind = METRICS.get(family.name, METRICS.get(f"{family.name}_total", ("gauge", "")))[0]
        assert family.type == kind, family.name
        for sample in family.samples:
            if family.type == "counter":
                assert sample.name == f"{family.name}_total", sample.name
            elif family.type == "gauge":
                assert not sample.name.endswith("_total"), sample.name
    assert {name for name, (kind, _) in METRICS.items() if kind == "counter"} == {
        name for name in METRICS if name.endswith("_total")
    }


def test_the_model_info_labels_survive_a_path_with_quotes_and_spaces():
    families = check_exposition(exposition(SCRAPED_STATE))
    (info,) = [s for f in families for s in f.samples if s.name == "fog_driver_model_info"]
    assert info.value == 1.0 and info.labels == SCRAPED_STATE["status"]["model_file"]


def test_the_shipped_alert_rules_and_scrape_job_pass_promtool(tmp_path):
    """The rules were a comment in prometheus.yml that nothing checked; now a rules file the scrape job names,
    checked by ``promtool check rules`` and, with the job's token file pointed at one that exists, ``promtool
    check config`` (which checks the rules file it names too)."""
    rules_path = MONITORING / "fog-driver-rules.yml"
    rules = yaml.safe_load(rules_path.read_text())
    exprs = {rule["alert"]: rule["expr"] for group in rules["groups"] for rule in group["rules"]}
    assert {"FogLinkDown", "FogFramesMissing", "FogNoSamples", "FogDaemonDown"} <= set(exprs)
    used = {name for e in exprs.values() for name in re.findall(r"fog_driver_\w+", e)}
    assert used <= set(METRICS) and not used & set(DEPRECATED_NAMES)
    config = yaml.safe_load((MONITORING / "prometheus.yml").read_text())
    assert config["rule_files"] == ["fog-driver-rules.yml"]
    promtool = shutil.which("promtool")
    if promtool is None:
        return  # read as YAML above; CI installs promtool
    done = subprocess.run([promtool, "check", "rules", str(rules_path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and f"SUCCESS: {len(exprs)} rules found" in done.stdout, done.stdout + done.stderr
    token = tmp_path / "fog-driver.token"
    token.write_text("a-long-token\n")
    for job in config["scrape_configs"]:
        job["authorization"]["credentials_file"] = str(token)
    shutil.copy(rules_path, tmp_path / "fog-driver-rules.yml")
    (tmp_path / "prometheus.yml").write_text(yaml.safe_dump(config))
    done = subprocess.run(
        [promtool, "check", "config", str(tmp_path / "prometheus.yml")], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_dashboard_reads_the_new_names():
    text = (MONITORING / "grafana-dashboard.json").read_text()
    assert not re.findall(r"fog_driver_\w+_dph\b", text)
    assert "fog_driver_drift_degrees_per_hour" in text and "fog_driver_rate_degrees_per_hour" in text
