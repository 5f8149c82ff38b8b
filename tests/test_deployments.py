"""Every deployment of deployments/prefect.yaml builds offline: entry point loads, parameters
validate against the flow's signature, schedules parse to the intended cron."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "deployments" / "prefect.yaml"


def _spec() -> dict:
    return yaml.safe_load(SPEC.read_text())


def _deployments():
    return {d["name"]: d for d in _spec()["deployments"]}


def test_the_three_deployments_exist():
    d = _deployments()
    assert set(d) == {"nightly-scan", "retry-failed", "train"}
    assert d["nightly-scan"]["work_pool"]["name"] == "cpu-pool"
    assert d["train"]["work_pool"]["name"] == "gpu-pool"


@pytest.mark.parametrize("name", ["nightly-scan", "retry-failed", "train"])
def test_deployment_builds_offline(name, monkeypatch):
    from prefect.flows import load_flow_from_entrypoint
    from prefect.schedules import Cron

    monkeypatch.chdir(ROOT)
    d = _deployments()[name]
    flow = load_flow_from_entrypoint(d["entrypoint"])
    params = d.get("parameters") or {}
    # every parameter is an argument of the flow, every required argument is given, types validate
    schema = flow.parameters
    assert set(params) <= set(schema.properties), set(params) - set(schema.properties)
    assert set(schema.required or []) <= set(params)
    flow.validate_parameters(params)
    schedules = [Cron(s["cron"], timezone=s.get("timezone")) for s in d.get("schedules") or []]
    dep = flow.to_deployment(name=name, parameters=params, schedules=schedules, tags=d.get("tags"),
                             work_pool_name=d["work_pool"]["name"], entrypoint_type=None)
    assert dep.entrypoint.replace("\\", "/").endswith(d["entrypoint"])
    assert dep.parameters == params
    assert dep.work_pool_name == d["work_pool"]["name"]
    crons = [s.schedule.cron for s in dep.schedules]
    assert crons == [s["cron"] for s in d.get("schedules") or []]


def test_schedules_are_what_the_service_promises():
    import asyncio
    import datetime as dt
    from zoneinfo import ZoneInfo

    from prefect.server.schemas.schedules import CronSchedule

    d = _deployments()
    nightly = d["nightly-scan"]["schedules"][0]
    tz = ZoneInfo(nightly["timezone"])
    sched = CronSchedule(cron=nightly["cron"], timezone=nightly["timezone"])
    dates = asyncio.run(sched.get_dates(n=3, start=dt.datetime(2026, 1, 1, 12, 0, tzinfo=tz)))
    local = [x.astimezone(tz) for x in dates]
    assert [(x.day, x.hour, x.minute) for x in local] == [(2, 1, 0), (3, 1, 0), (4, 1, 0)]  # nightly at 01:00
    assert d["retry-failed"]["schedules"][0]["cron"] == "0 6 * * *"
    assert d["train"]["schedules"] == []  # on demand only
    assert d["nightly-scan"]["parameters"]["drop"] != d["nightly-scan"]["parameters"]["out"]
    assert d["retry-failed"]["parameters"]["out"] == d["nightly-scan"]["parameters"]["out"]
