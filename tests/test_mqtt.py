"""MQTT: the probe publishing to a real mosquitto on loopback (seen by mosquitto_sub), its last
will on SIGKILL, Home Assistant discovery, hostlink's broker discovery and merged stream, and a
fleet of 50 simulated probes through one broker (#19)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lightprobe.bench.fleet import Mosquitto, Subscriber, SyntheticProbe
from lightprobe.core.errors import InputError
from lightprobe.core.mqtt_topics import parse_broker_url, probe_of_topic, topic
from lightprobe.device.sensors import (
    cct_mccamy,
    horizontal_illuminance,
    primary_angles,
    sensor_body,
)
from lightprobe.device.service.home_assistant import ha_discovery
from lightprobe.device.service.mqtt import MqttPublisher
from lightprobe.device.service.mqtt_settings import MqttSettings

MOSQUITTO = shutil.which("mosquitto") or (shutil.which("/usr/sbin/mosquitto"))
needs_broker = pytest.mark.skipif(MOSQUITTO is None or shutil.which("mosquitto_sub") is None,
                                  reason="Debian mosquitto / mosquitto-clients not installed")


# ---- the contract ---------------------------------------------------------------------------------
def test_broker_urls() -> None:
    a = parse_broker_url("mqtt://10.1.2.3")
    assert (a.host, a.port, a.tls, a.username) == ("10.1.2.3", 1883, False, None)
    b = parse_broker_url("mqtts://probe%40site@broker.example:18883")
    assert (b.host, b.port, b.tls, b.username) == ("broker.example", 18883, True, "probe@site")
    assert parse_broker_url(b.url) == b
    for bad, needle in [("http://x", "mqtt://HOST"), ("mqtt://", "mqtt://HOST"),
                        ("mqtt://u:secret@x", "password"), ("mqtt://x/topic", "no path"),
                        ("mqtt://x:99999", "not a broker URL")]:
        with pytest.raises(InputError, match=needle) as e:
            parse_broker_url(bad, "--mqtt")
        assert e.value.param == "--mqtt"


def test_topics_round_trip() -> None:
    t = topic("site/b2/lightprobe", "abc-1", "lights")
    assert t == "site/b2/lightprobe/abc-1/lights"
    assert probe_of_topic("site/b2/lightprobe", t) == ("abc-1", "lights")
    assert probe_of_topic("lightprobe", "lightprobe/abc/other") is None
    assert probe_of_topic("lightprobe", "elsewhere/abc/lights") is None


def _rgb_of_xy(x: float, y: float) -> np.ndarray:
    from lightprobe.device.sensors import RGB_TO_XYZ

    xyz = np.array([x / y, 1.0, (1 - x - y) / y])
    return np.linalg.solve(RGB_TO_XYZ, xyz)


@pytest.mark.parametrize(("x", "y", "kelvin"), [(0.31271, 0.32902, 6504), (0.44757, 0.40745, 2856),
                                                (0.34567, 0.35850, 5003)])
def test_cct_of_the_cie_illuminants(x: float, y: float, kelvin: float) -> None:
    # D65, A and D50: McCamy's cubic is within a few kelvin of the tabulated CCTs
    assert cct_mccamy(_rgb_of_xy(x, y)) == pytest.approx(kelvin, abs=6)
    assert cct_mccamy(np.ones(3)) == pytest.approx(6504, abs=6)  # linear Rec. 709 white = D65


def test_cct_of_nothing_is_none() -> None:
    assert cct_mccamy([0, 0, 0]) is None
    assert cct_mccamy([np.nan, 1, 1]) is None
    assert cct_mccamy([0, 0, 1]) is None  # pure blue is far off the locus


def test_primary_angles_follow_the_conventions() -> None:
    assert primary_angles([0, 1, 0])[0] == pytest.approx(90)
    # theta = 60 deg from zenith, phi = 30 deg: d = (sin t sin p, cos t, -sin t cos p)
    t, p = math.radians(60), math.radians(30)
    d = [math.sin(t) * math.sin(p), math.cos(t), -math.sin(t) * math.cos(p)]
    assert primary_angles(d) == pytest.approx((30.0, 30.0), abs=1e-3)
    assert primary_angles([0.0, -0.5, 0.5])[1] == pytest.approx(180.0)
    assert primary_angles(None) == (None, None)


def test_horizontal_illuminance_is_the_meters_integral() -> None:
    from lightprobe.calibration.photometric import upper_irradiance

    rng = np.random.default_rng(3)
    img = rng.uniform(0, 5, (64, 128, 3)).astype(np.float32)
    img[3, 7, 1] = np.nan
    rgb = horizontal_illuminance(img)
    y = float(rgb @ np.array([0.2126, 0.7152, 0.0722]))
    assert y == pytest.approx(upper_irradiance(img), rel=1e-6)
    # a uniform sky of radiance L gives pi L on a horizontal surface
    assert horizontal_illuminance(np.full((90, 180, 3), 2.0)) == pytest.approx(np.full(3, 2 * math.pi), rel=1e-9)
    body = sensor_body(rgb, "nit", [0, 1, 0], "ok", 7, 1.5)
    assert body["illuminance_unit"] == "lx"
    assert body["elevation"] == pytest.approx(90)
    json.dumps(body, allow_nan=False)


# Home Assistant's MQTT sensor options (https://www.home-assistant.io/integrations/sensor.mqtt/),
# device options and the device classes' units we use
HA_SENSOR_KEYS = {
    "availability", "availability_mode", "availability_template", "availability_topic", "device",
    "device_class", "enabled_by_default", "encoding", "entity_category", "entity_picture",
    "expire_after", "force_update", "icon", "json_attributes_template", "json_attributes_topic",
    "last_reset_value_template", "name", "object_id", "options", "origin", "payload_available",
    "payload_not_available", "platform", "qos", "state_class", "state_topic",
    "suggested_display_precision", "unique_id", "unit_of_measurement", "value_template",
    "default_entity_id"}
HA_DEVICE_KEYS = {"configuration_url", "connections", "hw_version", "identifiers", "manufacturer",
                  "model", "model_id", "name", "serial_number", "suggested_area", "sw_version",
                  "via_device"}
HA_STATE_CLASSES = {"measurement", "total", "total_increasing", "measurement_angle"}


def _check_ha_sensor(t: str, cfg: dict[str, Any], probe_id: str) -> None:
    assert set(cfg) <= HA_SENSOR_KEYS, set(cfg) - HA_SENSOR_KEYS
    assert set(cfg["device"]) <= HA_DEVICE_KEYS
    parts = t.split("/")
    assert parts[0] == "homeassistant"
    assert parts[1] == "sensor"
    assert parts[-1] == "config"
    assert parts[2] == f"lightprobe_{probe_id}"
    assert len(parts) == 5
    assert cfg["unique_id"].startswith(f"lightprobe_{probe_id}_")
    assert cfg["state_topic"] == f"lightprobe/{probe_id}/sensors"
    assert cfg["availability_topic"] == f"lightprobe/{probe_id}/status"
    assert cfg["device"]["identifiers"] == [f"lightprobe_{probe_id}"]
    assert cfg.get("state_class", "measurement") in HA_STATE_CLASSES
    if cfg.get("device_class") == "illuminance":
        assert cfg["unit_of_measurement"] == "lx"
    if cfg.get("device_class") == "enum":
        assert "unit_of_measurement" not in cfg
        assert cfg["options"]
    assert cfg["value_template"].startswith("{{ value_json.")


@pytest.mark.parametrize(("unit", "lux"), [("nit", True), ("relative", False)])
def test_home_assistant_discovery_configs(unit: str, lux: bool) -> None:
    s = MqttSettings(parse_broker_url("mqtt://127.0.0.1"))
    status = {"name": "Hall", "model": "lp1", "sw_version": "0.1.0", "url": "http://10.0.0.9:8080"}
    msgs = ha_discovery("p1", status, unit, s)
    assert len({t for t, _ in msgs}) == 5
    by_obj = {t.split("/")[3]: c for t, c in msgs}
    for t, c in msgs:
        _check_ha_sensor(t, c, "p1")
        json.dumps(c, allow_nan=False)
    ill = by_obj["illuminance"]
    assert (ill.get("device_class") == "illuminance") is lux
    assert (ill.get("unit_of_measurement") == "lx") is lux
    assert by_obj["colour_temperature"]["unit_of_measurement"] == "K"
    assert by_obj["health"]["options"] == ["ok", "degraded", "starting"]


def test_mqtt_config_is_checked(tmp_path: Path) -> None:
    from lightprobe.device.service.config import ServiceConfig

    cfg = ServiceConfig()
    assert MqttSettings.from_config(cfg, env={}) is None
    with pytest.raises(InputError) as e:
        cfg.with_patch({"mqtt": {"url": "mqtt://user:pw@host"}})
    assert e.value.param == "mqtt.url"
    with pytest.raises(InputError, match=r"mqtt\.topic_prefix"):
        cfg.with_patch({"mqtt": {"topic_prefix": "a/+/b"}})
    pw = tmp_path / "pw"
    pw.write_text("s3cret\n")
    c2 = cfg.with_patch({"mqtt": {"url": "mqtts://u@b.example", "password_file": str(pw), "keepalive": 5}})
    s = MqttSettings.from_config(c2, env={})
    assert s is not None
    assert (s.broker.tls, s.broker.username, s.password, s.keepalive) == (True, "u", "s3cret", 5)
    c3 = cfg.with_patch({"mqtt": {"url": "mqtt://b", "password_file": str(tmp_path / "missing")}})
    with pytest.raises(InputError, match="password_file"):
        MqttSettings.from_config(c3, env={})


def test_serve_with_a_bad_broker_url_exits_2(tmp_path: Path) -> None:
    from tests.test_service_cli import ROOT, SERVE, _env

    p = subprocess.run([os.sys.executable, str(SERVE), "--port", "0", "--state-dir", str(tmp_path),  # type: ignore[attr-defined]
                        "--mqtt", "http://nope"], cwd=ROOT, env=_env(), capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 2
    assert "--mqtt" in p.stderr


# ---- the real broker --------------------------------------------------------------------------------
@pytest.fixture
def broker() -> Iterator[Mosquitto]:
    with Mosquitto() as b:
        yield b


@needs_broker
def test_the_probe_on_mosquitto_and_its_last_will(tmp_path: Path, broker: Mosquitto) -> None:
    from lightprobe.core.lightset import LightSet
    from lightprobe.device.service.config import dump_toml
    from tests.test_service_cli import start_serve

    state = tmp_path / "state"
    state.mkdir()
    (state / "config.toml").write_text(dump_toml({
        "mdns": {"enabled": False}, "probe": {"id": "hall-1", "name": "Hall"},
        "pipeline": {"fps": 10.0, "light_count": 32},
        "mqtt": {"keepalive": 2, "sensors_rate": 2.0, "status_interval": 5.0}}))
    sub = Subscriber(broker.url, "lightprobe/#", "homeassistant/#")
    p, url, _token = start_serve(state, "--mqtt", broker.url)
    try:
        _, _, body = sub.wait(lambda t, b: t == "lightprobe/hall-1/lights", 60)
        ls = LightSet.from_json(json.loads(body))
        assert ls.probe == "hall-1"
        assert len(ls.directions) == 32
        _, _, st = sub.wait(lambda t, b: t == "lightprobe/hall-1/status", 5)
        status = json.loads(st)
        assert status["state"] == "online"
        assert status["url"] == url
        assert status["name"] == "Hall"
        _, _, sens = sub.wait(lambda t, b: t == "lightprobe/hall-1/sensors", 10)
        sensors = json.loads(sens)
        assert sensors["illuminance"] > 0
        assert sensors["illuminance_unit"] == "relative"
        assert sensors["health"] in ("ok", "starting", "degraded")
        sub.wait(lambda t, b: t == "lightprobe/hall-1/sh", 10)
        configs = [(t, json.loads(b)) for _, t, b in sub.lines if t.startswith("homeassistant/")]
        assert len({t for t, _ in configs}) == 5
        for t, c in configs:
            _check_ha_sensor(t, c, "hall-1")
        # SIGKILL: no goodbye; the broker publishes the will after 1.5 x keepalive of silence
        t_kill = time.monotonic()
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        t_off, _, off = sub.wait(lambda t, b: t == "lightprobe/hall-1/status" and '"offline"' in b, 15)
        assert json.loads(off) == {"version": 1, "probe": "hall-1", "state": "offline"}
        print(f"last will after {t_off - t_kill:.2f} s (keepalive 2 s)")
    finally:
        if p.poll() is None:
            p.kill()
        sub.close()
    # retained: a subscriber that comes later still learns the probe is offline, and its last lights
    late = Subscriber(broker.url, "lightprobe/hall-1/#")
    try:
        late.wait(lambda t, b: t.endswith("/status") and '"offline"' in b, 5)
        late.wait(lambda t, b: t.endswith("/lights"), 5)
    finally:
        late.close()


@needs_broker
def test_a_frozen_probe_goes_offline_after_its_keepalive(broker: Mosquitto) -> None:
    """SIGKILL closes the socket, so the broker publishes the will at once; a probe that hangs
    or loses its network keeps the socket open: the will then comes after 1.5 x keepalive."""
    import sys

    from tests.test_service_cli import ROOT

    sub = Subscriber(broker.url, "lightprobe/fleet000/status")
    child = subprocess.Popen([sys.executable, "-m", "lightprobe.bench.fleet", broker.url, "1", "10", "60", "2"],
                             cwd=ROOT, stdout=subprocess.DEVNULL)
    try:
        sub.wait(lambda t, b: '"online"' in b, 30)
        t0 = time.monotonic()
        child.send_signal(signal.SIGSTOP)
        t_off, _, _ = sub.wait(lambda t, b: '"offline"' in b, 15)
        print(f"frozen probe offline after {t_off - t0:.2f} s (keepalive 2 s)")
        # the keepalive's doing, not a closed socket: the process (and so its socket) is still there
        assert child.poll() is None
    finally:
        child.kill()
        child.wait(5)
        sub.close()


@needs_broker
async def test_a_clean_stop_says_offline_and_hostlink_discovery_follows(broker: Mosquitto) -> None:
    from lightprobe.hostlink.discovery import Discovery, ProbeEvent

    events: list[ProbeEvent] = []
    settings = MqttSettings(parse_broker_url(broker.url), sh_rate=0.0, discovery=False)
    probe = SyntheticProbe("syn-1")
    pub = MqttPublisher(probe, settings)
    async with Discovery(mdns=False, brokers=[broker.url], liveness_s=None, on_event=events.append) as d:
        pub.start()
        await d.wait_for(lambda ps: "syn-1" in ps, within=10)
        info = d.probes["syn-1"]
        assert (info.source, info.service_name, info.name) == ("mqtt", broker.url, "sim syn-1")
        await pub.stop()
        await d.wait_for(lambda ps: "syn-1" not in ps, within=10)
    assert [e.kind for e in events] == ["added", "removed"]
    assert pub.counters.published.get("status", 0) >= 2  # online, then offline


@needs_broker
async def test_a_broker_that_comes_later_is_reached() -> None:
    port = __import__("lightprobe.bench.fleet", fromlist=["free_port"]).free_port()
    settings = MqttSettings(parse_broker_url(f"mqtt://127.0.0.1:{port}"), sh_rate=0.0, discovery=False)
    pub = MqttPublisher(SyntheticProbe("late-1"), settings, backoff=(0.1, 0.2))
    pub.start()
    await asyncio.sleep(0.5)
    assert not pub.connected
    assert pub.counters.last_error
    with Mosquitto(port):
        for _ in range(600):  # 30 s: a hang guard, 10x the longest reconnect seen here
            if pub.connected:
                break
            await asyncio.sleep(0.05)
        assert pub.connected, "hung: the publisher never reached the broker that came up later"
        await pub.stop()


@needs_broker
async def test_fifty_probes_through_one_broker_into_one_merge(broker: Mosquitto) -> None:
    """50 simulated probes (the service's publisher, synthetic lights) at 10 Hz for 3 s; the host
    merges all of them from the broker and sees their frames as they go (latency is a benchmark
    figure: ``lightprobe bench fleet``)."""
    from lightprobe.bench.fleet import run_fleet
    from lightprobe.hostlink.stream import MergedStream

    frames: dict[str, set[int]] = {}
    biggest = 0

    async def consume(ms: MergedStream) -> None:
        nonlocal biggest
        async for merged in ms.updates(idle=30.0):  # 50 connections first: no frames meanwhile
            for pid, ls in ms.latest().items():
                frames.setdefault(pid, set()).add(ls.frame)
            biggest = max(biggest, len(merged.extra["merged_from"]))
            assert merged.extra["merge"] == "index"

    async with MergedStream(broker.url, count=64, method="auto", stale_after=2.0) as ms:
        fleet = asyncio.create_task(run_fleet(broker.url, 50, 10.0, 3.0))
        consumer = asyncio.create_task(consume(ms))
        # The fleet's end is not a change the stream must report (the last frames may all be
        # merged before it returns), so the fleet, not the stream, ends the test.
        done, _ = await asyncio.wait({consumer, fleet}, return_when=asyncio.FIRST_COMPLETED)
        if consumer in done:
            consumer.result()  # an assertion or the idle timeout: raise it here
        out = await fleet
        consumer.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await consumer
    assert biggest == 50
    assert len(frames) == 50
    seen = sum(len(v) for v in frames.values())
    assert seen >= 0.5 * out["published"], (seen, out)  # a merge each few frames, newest wins
    assert out["published"] >= 50  # (how many in the 3 s, and how late: lightprobe bench fleet)
