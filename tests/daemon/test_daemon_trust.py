"""What the daemon trusts, and how it reloads (issue 12's review: M1, M2, M3, M4, M6, H6, C1), without sockets.

Each test names the finding it holds; each failed on the code before its fix."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from framegen import with_identities
from service_in_process import offline, publish

from fog_driver.compensation.adapt import AdaptConfig
from fog_driver.compensation.binding import ModelMismatchError
from fog_driver.compensation.fitting.data import FitConfig
from fog_driver.daemon.config import DriverConfig
from fog_driver.daemon.service import Service
from fog_driver.errors import InputFileError
from fog_driver.flags import FLAG_ADAPTING, FLAG_GAP
from fog_driver.modelfiles import load_model, save_model
from fog_driver.offline.fit import fit_model_file
from fog_driver.protocol import decode_bytes

DATA = Path(__file__).resolve().parents[1] / "data"
SHORT = (DATA / "sim-short.bin").read_bytes()


# -- M6: IDENTITY fields from the wire ------------------------------------------------------------


@pytest.mark.parametrize(
    "fields",
    [
        {"rate_hz": 0},
        {"scale_arcsec_per_count": math.nan},
        {"scale_arcsec_per_count": -0.01},
        {"scale_arcsec_per_count": math.inf},
    ],
)
def test_an_implausible_identity_is_counted_and_ignored_the_angle_stays_finite(fields):
    """Rate 0 crashed the daemon (ZeroDivisionError); one NaN scale removed angle_arcsec from every later ANGLE."""
    half = len(SHORT) // 2
    data = with_identities(SHORT, half, **fields)
    service = Service(DriverConfig(), port="unused")
    published = publish(service, data)
    assert len(published) == 3000
    assert all(math.isfinite(o["angle_arcsec"]) and math.isfinite(o["rate_dph"]) for o in published)
    assert service.status_object()["identities_rejected"] == sum(
        f.offset >= half for f in decode_bytes(data).identities
    )
    assert service.identity.rate_hz == 10  # the last plausible one stays in force
    assert [o["angle_arcsec"] for o in published] == [
        o["angle_arcsec"] for o in publish(Service(DriverConfig(), port="u"), SHORT)
    ]


def test_an_implausible_first_identity_leaves_samples_waiting_for_a_plausible_one():
    data = with_identities(SHORT, 0, rate_hz=0)
    service = Service(DriverConfig(), port="unused")
    assert publish(service, data) == []
    assert len(service.samples_before_identity) == 3000 and service.compensator is None


# -- M2: the model is bound to an instrument --------------------------------------------------------


def test_a_model_for_another_instrument_is_refused_at_the_first_identity_unless_forced():
    data = with_identities(SHORT, 0, serial="FOG-OTHER-9999")
    service = Service(DriverConfig(), port="unused")
    with pytest.raises(ModelMismatchError, match="FOG-OTHER-9999.*force_model"):
        publish(service, data)
    forced = Service(DriverConfig(force_model=True), port="unused")
    assert len(publish(forced, data)) == 3000


def test_a_rate_change_mid_run_rebuilds_the_pipeline_flags_it_and_offline_does_the_same(tmp_path):
    """The daemon kept the old frame period: rate_dph and the drift per frame off by the rate ratio."""
    cut = len(SHORT) // 2
    data = with_identities(SHORT, cut, rate_hz=20)
    path = tmp_path / "changed.bin"
    path.write_bytes(data)
    service = Service(DriverConfig(), port="unused")
    published = publish(service, data)
    angles, flags = offline(path)
    assert [o["angle_arcsec"] for o in published] == angles  # live == offline through the change
    first_after = next(
        i
        for i, o in enumerate(published)
        if o["seq"] and service.identity.rate_hz == 20 and "gap" in o["flags"] and i > 100
    )
    assert flags[first_after] & FLAG_GAP
    assert service.status_object()["instrument_changes"] == 1
    assert service.compensator.frame_period_s == 1 / 20
    # the rate published after the change uses the new period: 10 Hz frames read as 20 Hz double it
    before = np.mean([o["rate_raw_dph"] for o in published[100:1000]])
    after = np.mean([o["rate_raw_dph"] for o in published[-900:]])
    assert after == pytest.approx(2 * before, rel=0.2)


def test_another_serial_mid_run_is_refused_like_at_the_start():
    data = with_identities(SHORT, len(SHORT) // 2, serial="FOG-OTHER-9999")
    service = Service(DriverConfig(), port="unused")
    with pytest.raises(ModelMismatchError):
        publish(service, data)


# -- M1: the adaptation state after a re-fit ---------------------------------------------------------


@pytest.fixture(scope="module")
def other_model(tmp_path_factory):
    model_file, _ = fit_model_file(
        [DATA / "sim-short.bin"], kind="polynomial", config=FitConfig(warmup_s=30.0), accept_weak=True
    )
    return save_model(tmp_path_factory.mktemp("m") / "poly.yaml", model_file)


def test_a_state_saved_for_another_model_is_set_aside_at_start_with_a_warning(tmp_path, other_model):
    """It made the next start exit 65 after READY (a restart loop)."""
    state = tmp_path / "adapt.yaml"
    first = Service(DriverConfig(adapt_state=str(state), adapt_reference_dph=0.0), port="unused")
    publish(first, SHORT)
    first.shutdown()
    assert state.exists()
    refit = Service(DriverConfig(adapt_state=str(state), model=str(other_model)), port="unused")
    assert not state.exists() and len(list(tmp_path.glob("adapt.yaml.stale-*"))) == 1
    assert len(publish(refit, SHORT)) == 3000


def test_a_table_state_an_earlier_version_learned_on_the_models_own_regressors_is_set_aside(tmp_path):
    """The table law learns on the shipped model's candidate structures; a state learned on its own regressors
    (saved before, without ``shape``) cannot be carried on: set aside at start, the daemon runs."""
    from fog_driver.compensation.table import TableLaw
    from fog_driver.daemon.config import DEFAULT_MODEL

    state = tmp_path / "adapt.yaml"
    first = Service(DriverConfig(adapt_state=str(state), adapt_reference_dph=0.0), port="unused")
    publish(first, SHORT)
    first.shutdown()
    model = load_model(DEFAULT_MODEL).model
    earlier = TableLaw(model.weights, model.intercept, 1.0, shape="regressors").get_state()
    del earlier["shape"]
    doc = yaml.safe_load(state.read_text())
    state.write_text(yaml.safe_dump({**doc, "table": earlier}))
    Service(DriverConfig(adapt_state=str(state), adapt_reference_dph=0.0), port="unused")
    assert not state.exists() and len(list(tmp_path.glob("adapt.yaml.stale-*"))) == 1


def test_the_state_is_saved_at_exit_only_when_adaptation_ran(tmp_path):
    state = tmp_path / "adapt.yaml"
    frozen = Service(DriverConfig(adapt_state=str(state)), port="unused")
    publish(frozen, SHORT)
    frozen.shutdown()
    assert not state.exists()
    adapting = Service(DriverConfig(adapt_state=str(state)), port="unused")
    publish(adapting, SHORT[:20000])
    assert adapting.control("ADAPT", {"enable": True, "reference_dph": 0.0}, 0)["class"] == "ADAPT"
    publish(adapting, SHORT[20000:])
    adapting.shutdown()
    assert state.exists()


# -- M3 / H6 / transactional reloads ------------------------------------------------------------------


class FakeHub:
    def __init__(self) -> None:
        self.calls: list = []
        self.clients = self.dropped_clients = 0

    def check_token(self, token):
        if token is None:
            raise ValueError("refusing to listen beyond loopback without a token")

    def set_token(self, token):
        self.calls.append(("token", token))

    def set_max_backlog_s(self, seconds):
        self.calls.append(("backlog", seconds))

    def publish(self, obj):
        pass


def test_sighup_with_an_unrelated_change_changes_nothing_published_and_keeps_adapt():
    """A SIGHUP meant for one setting rebuilt the compensator (0.61" for good) and undid ?ADAPT."""
    expected = publish(Service(DriverConfig(), port="u"), SHORT)
    service = Service(DriverConfig(), port="unused")
    service.hub = FakeHub()
    before = publish(service, SHORT[:40000])
    service.control("ADAPT", {"enable": True, "reference_dph": 0.0}, 0)
    result = service.reload_config(DriverConfig(status_every_s=5.0, token="a-long-token", max_client_backlog_s=3.0))
    assert result["changed"] is False and result["restart_needed"] == []
    assert set(result["applied"]) == {"status_every_s", "token", "max_client_backlog_s"}
    assert service.config.status_every_s == 5.0
    assert service.hub.calls == [("token", "a-long-token"), ("backlog", 3.0)]
    assert service.compensator.reference_rate_dph == 0.0  # the client's ?ADAPT stands
    service.control("ADAPT", {"enable": False}, 0)
    after = publish(service, SHORT[40000:])
    assert [o["angle_arcsec"] for o in before + after] == [o["angle_arcsec"] for o in expected]


def test_a_reload_that_fails_changes_nothing(tmp_path, other_model):
    service = Service(DriverConfig(), port="unused")
    service.hub = FakeHub()
    publish(service, SHORT[:20000])
    model_before, compensator_before = service.model_file, service.compensator
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: nonsense\n")
    with pytest.raises(InputFileError):
        service.reload_config(DriverConfig(model=str(bad), token="a-long-token"))
    assert service.config.token is None and service.hub.calls == []  # nothing applied, not even the token
    assert service.model_file is model_before and service.compensator is compensator_before
    exposed = Service(DriverConfig(listen="0.0.0.0:2948", token="a-long-token"), port="unused")
    exposed.hub = FakeHub()
    publish(exposed, SHORT[:20000])
    model_before, compensator_before = exposed.model_file, exposed.compensator
    with pytest.raises(ValueError):  # the token removed while listening beyond loopback: refused first
        exposed.reload_config(DriverConfig(model=str(other_model), token=None, listen="0.0.0.0:2948"))
    assert exposed.model_file is model_before and exposed.compensator is compensator_before
    assert exposed.config.token == "a-long-token" and exposed.hub.calls == []
    reply = service.control("RELOAD", {}, 0)
    assert reply["class"] == "RELOAD" and reply["changed"] is False


def test_a_token_the_web_view_refuses_changes_nothing_on_either_listener():
    """Only the NDJSON hub was asked: a web view beyond loopback refused the token's removal after the hub had
    applied it (the hub then open, the web view still closed)."""

    class LoopbackHub(FakeHub):
        def check_token(self, token):
            pass

    class ExposedWeb(FakeHub):
        max_backlog_s = 2.0

    service = Service(DriverConfig(token="a-long-token", http="0.0.0.0:8948"), port="unused")
    service.hub, service.web = LoopbackHub(), ExposedWeb()
    with pytest.raises(ValueError):
        service.reload_config(DriverConfig(token=None, http="0.0.0.0:8948"))
    assert service.hub.calls == [] and service.web.calls == [] and service.config.token == "a-long-token"


def test_a_model_for_another_instrument_is_refused_by_reload_and_nothing_changes(tmp_path, other_model):
    model_file = load_model(other_model)
    foreign = save_model(
        tmp_path / "foreign.yaml",
        model_file.__class__(**{**model_file.__dict__, "instrument_serial": "FOG-OTHER-9999"}),
    )
    service = Service(DriverConfig(), port="unused")
    publish(service, SHORT[:20000])
    before = service.model_file
    with pytest.raises(ModelMismatchError):
        service.reload_config(DriverConfig(model=str(foreign)))
    assert service.model_file is before and service.version_object()["model"] == before.kind


# -- M4: live == offline under the documented settings -------------------------------------------------


def test_live_equals_offline_with_a_scale_override(tmp_path):
    """3000 of 3000 angles differed: compensate had no scale override."""
    service = Service(DriverConfig(scale_override_arcsec_per_count=0.0100001), port="unused")
    published = publish(service, SHORT)
    angles, _ = offline(DATA / "sim-short.bin", scale_override_arcsec_per_count=0.0100001)
    assert [o["angle_arcsec"] for o in published] == angles
    assert angles != offline(DATA / "sim-short.bin")[0]


def test_live_equals_offline_with_a_restored_adaptation_state(tmp_path):
    """A daemon that restored a state gave weights `compensate` could not reproduce (--adapt-state needed a
    reference, and then adapted further)."""
    state = tmp_path / "adapt.yaml"
    first = Service(DriverConfig(adapt_state=str(state), adapt_reference_dph=0.0), port="unused")
    publish(first, (DATA / "sim-faults.bin").read_bytes())
    first.shutdown()
    doc = yaml.safe_load(state.read_text())
    doc["readout"]["law"]["w"][-1] += 0.01  # weights of its own (a 5-min run never leaves the bias capture)
    state.write_text(yaml.safe_dump(doc))
    service = Service(DriverConfig(adapt_state=str(state)), port="unused")  # frozen, with the adapted weights
    published = publish(service, SHORT)
    angles, flags = offline(DATA / "sim-short.bin", adapt=AdaptConfig(), adapt_state=state, save_adapt_state=False)
    assert [o["angle_arcsec"] for o in published] == angles
    assert [bool("adapting" in o["flags"]) for o in published] == [bool(f & FLAG_ADAPTING) for f in flags]
    assert state.read_text() == yaml.safe_dump(doc)  # only read: neither saved it


# -- C1: a bias answer nobody waits for ---------------------------------------------------------------


def test_a_bias_capture_whose_client_left_completes_and_applies_without_an_error():
    """The hub cancelled the future and set_result raised in the acquisition thread: exit 1.  Now nothing
    waits on a capture: it is acknowledged at once, and its result is an event for whoever is connected."""
    service = Service(DriverConfig(), port="unused")
    publish(service, SHORT[:10000])
    started = service.control("BIAS", {"seconds": 5}, 0)
    assert started["state"] == "started" and started["timeout_s"] == pytest.approx(5 + 30.0)
    rest = publish(service, SHORT[10000:])
    assert len(rest) > 0 and service.bias_dph != 0.0  # applied
    assert service.last_event["state"] == "done"


def test_a_bias_capture_without_data_fails_at_its_deadline_and_keeps_the_bias(monkeypatch):
    """The port went away: the capture is abandoned after its seconds plus the margin (a BIAS failed event),
    never applied later out of the blue; a new one may start."""
    import fog_driver.daemon.commands as service_module

    monkeypatch.setattr(service_module, "BIAS_ANSWER_MARGIN_S", 0.05)
    service = Service(DriverConfig(), port="unused")

    class Hub:
        def __init__(self) -> None:
            self.published: list[dict] = []
            self.done = threading.Event()

        def publish(self, obj):
            if obj["class"] == "BIAS":  # (DEVICE objects too, at the IDENTITY)
                self.published.append(obj)
                self.done.set()

    service.hub = hub = Hub()
    publish(service, SHORT[:10000])
    started = service.control("BIAS", {"seconds": 1}, 0)
    assert hub.done.wait(30.0)  # a bound, not a synchronization: the timer fires after 1.05 s
    (event,) = hub.published
    assert event["state"] == "failed" and event["capture_id"] == started["capture_id"] and "reason" in event
    service.hub = None
    assert service.bias_dph == 0.0 and service.status_object()["bias_captured"] is False
    assert service.control("BIAS", {"seconds": 1}, 0)["state"] == "started"  # not "already running"
    service.shutdown()
