"""Stream scheduling (rates, SET_MESSAGE_INTERVAL) and the PX4 parameter table."""

import pytest
from pymavlink.dialects.v20 import common as mavlink

from sim.sitl.params import INT32, REAL32, Param, ParamError, ParamTable
from sim.sitl.streams import DEFAULT_RATES_HZ, StreamScheduler

HB = mavlink.MAVLINK_MSG_ID_HEARTBEAT
ATT = mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION


def _count(scheduler: StreamScheduler, msg_id: int, t0: float, seconds: float, tick_s: float = 0.01) -> int:
    ticks = round(seconds / tick_s)
    return sum(msg_id in scheduler.due(t0 + i * tick_s) for i in range(ticks))


def test_default_rates_without_drift():
    scheduler = StreamScheduler(100.0, max_rate_hz=100.0)
    assert _count(scheduler, ATT, 100.0, 10.0) == 500
    scheduler = StreamScheduler(100.0, max_rate_hz=100.0)
    assert _count(scheduler, HB, 100.0, 10.0) == 10


def test_everything_goes_out_on_the_first_tick():
    scheduler = StreamScheduler(5.0, max_rate_hz=100.0)
    assert set(scheduler.due(5.0)) == set(DEFAULT_RATES_HZ)


def test_set_message_interval():
    scheduler = StreamScheduler(0.0, max_rate_hz=100.0)
    assert scheduler.set_interval(HB, 200_000, 0.0)  # 5 Hz
    assert _count(scheduler, HB, 0.0, 2.0) == 10
    assert scheduler.set_interval(ATT, 1_000, 2.0)  # 1 kHz asked, limited to the loop rate
    assert _count(scheduler, ATT, 2.0, 1.0) == 100
    assert scheduler.set_interval(ATT, -1, 3.0)  # stop
    assert _count(scheduler, ATT, 3.0, 1.0) == 0
    assert scheduler.set_interval(ATT, 0, 4.0)  # back to the default 50 Hz
    assert _count(scheduler, ATT, 4.0, 1.0) == 50
    assert not scheduler.set_interval(mavlink.MAVLINK_MSG_ID_BATTERY_STATUS, 1e6, 5.0)


def test_a_late_loop_does_not_burst():
    scheduler = StreamScheduler(0.0, max_rate_hz=100.0)
    scheduler.due(0.0)
    assert scheduler.due(3.0).count(HB) == 1
    assert HB not in scheduler.due(3.5)


def test_params_by_name_and_index():
    params = ParamTable(takeoff_alt_m=1.25)
    assert params["MIS_TAKEOFF_ALT"] == 1.25 and params["COM_OF_LOSS_T"] == 1.0
    names = [p.name for p in params.all()]
    assert names == sorted(names)
    assert params.find("", params.index_of("SYS_HITL")).name == "SYS_HITL"
    with pytest.raises(ParamError, match="unknown parameter"):
        params.find("NOPE", -1)
    with pytest.raises(ParamError, match="out of range"):
        params.find("", len(params))


def test_param_set_float_and_bytewise_int():
    params = ParamTable(takeoff_alt_m=1.0)
    params.set_from_wire("MIS_TAKEOFF_ALT", 2.5, REAL32)
    assert params["MIS_TAKEOFF_ALT"] == 2.5
    wire = ParamTable.wire_value(Param("SYS_HITL", 1, INT32))
    assert wire != 1.0  # the int's bytes, not its value
    params.set_from_wire("SYS_HITL", wire, INT32)
    assert params.find("SYS_HITL", -1).value == 1 and ParamTable.wire_value(params.find("SYS_HITL", -1)) == wire
    with pytest.raises(ParamError, match="MAV_PARAM_TYPE"):
        params.set_from_wire("MIS_TAKEOFF_ALT", 2.0, INT32)
