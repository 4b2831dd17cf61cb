"""The SITL vehicle's self-inflicted faults (sim.sitl.faults) and the hooks they act through."""

import socket
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from runtime.camera import Frame
from runtime.camera.validate import FrameValidator
from runtime.faults.catalogue import FaultKind, Injection, InjectionError
from sim.sitl.commander import ACCEPTED, DENIED, Commander
from sim.sitl.faults import FUTURE_STAMP_S, VehicleFaults
from sim.sitl.mavlink_endpoint import MavlinkEndpoint
from sim.sitl.params import ParamTable
from sim.sitl.px4 import HOLD, OFFBOARD, POSCTL
from tests.sim.sitl.test_commander import HOME, flying, hover_setpoint, kin

T_OFFBOARD = 100.0


def _faults(*injections: str) -> VehicleFaults:
    faults = VehicleFaults([Injection(FaultKind(k), float(at)) for k, at in (i.split("@") for i in injections)])
    faults.note_offboard(T_OFFBOARD)
    return faults


def _frame(t_s: float, seq: int = 0) -> Frame:
    return Frame(int(t_s * 1e9), np.full((120, 212), 3.0, np.float32), np.full((120, 212), 90, np.uint8), seq)


def test_faults_start_at_their_time_after_the_first_offboard_entry():
    faults = VehicleFaults([Injection(FaultKind.CAMERA_STALL, 2.0)])
    assert faults.camera_frame(_frame(50.0), 50.0) is not None  # before offboard: nothing
    faults.note_offboard(T_OFFBOARD)
    faults.note_offboard(T_OFFBOARD + 5.0)  # re-entries do not move the schedule
    assert faults.camera_frame(_frame(101.9), 101.9) is not None
    assert faults.camera_frame(_frame(102.0), 102.0) is None
    assert faults.injected == {FaultKind.CAMERA_STALL: 102.0}


def test_blackout_invalidates_all_depth_and_keeps_gray():
    faults = _faults("camera-blackout@0")
    out = faults.camera_frame(_frame(T_OFFBOARD), T_OFFBOARD)
    assert np.all(out.depth_m == 0.0) and np.all(out.gray_u8 == 90) and out.meta["invalid_depth_frac"] == 1.0
    assert FrameValidator().problem(out, out.t_capture_ns) is None  # degraded, not garbage


def test_garbage_frames_are_all_rejected_by_the_runtime():
    faults = _faults("camera-garbage@0")
    validator = FrameValidator()
    good = _frame(T_OFFBOARD - 0.1)
    assert validator.problem(good, good.t_capture_ns) is None
    forms = []
    for k in range(6):
        t_s = T_OFFBOARD + k / 15
        out = faults.camera_frame(_frame(t_s, seq=k), t_s)
        problem = validator.problem(out, int(t_s * 1e9))
        assert problem is not None, out.meta
        forms.append(out.meta["fault"])
    assert forms[:3] == ["camera-garbage:bits", "camera-garbage:shape", "camera-garbage:future"]
    assert forms[3:] == forms[:3]


def test_future_stamped_garbage_keeps_the_image():
    faults = _faults("camera-garbage@0")
    for k in range(3):
        out = faults.camera_frame(_frame(T_OFFBOARD, seq=k), T_OFFBOARD)
    assert out.t_capture_ns == pytest.approx((T_OFFBOARD + FUTURE_STAMP_S) * 1e9) and np.all(out.depth_m == 3.0)


def test_pilot_switches_once_and_offboard_refusal_holds_from_the_start():
    faults = _faults("pilot-takeover@2")
    assert not faults.pilot_takes_over(101.0)
    assert faults.pilot_takes_over(102.0) and not faults.pilot_takes_over(102.01)
    refusing = VehicleFaults([Injection(FaultKind.OFFBOARD_REFUSED, 0.0)])
    assert refusing.refuses_offboard and not refusing.offboard_allowed(5.0)
    assert refusing.injected == {FaultKind.OFFBOARD_REFUSED: 5.0}
    assert VehicleFaults([]).offboard_allowed(5.0)


def test_runtime_faults_are_not_the_vehicles():
    with pytest.raises(InjectionError, match="nan-action is not injected by the SITL vehicle"):
        VehicleFaults([Injection(FaultKind.NAN_ACTION, 1.0)])


def test_commander_refuses_offboard_when_told_and_follows_the_rc_switch():
    refusing = Commander(ParamTable(takeoff_alt_m=1.5), HOME, kin(), 0.0, offboard_allowed=lambda t_s: False)
    air = flying(refusing)
    refusing.on_setpoint(hover_setpoint(2.0))
    assert refusing.set_mode(2.0, air, OFFBOARD) == DENIED and refusing.mode == HOLD
    assert refusing.drain_events()[-1].text == "Offboard denied: mode not available"
    assert refusing.rc_mode_switch(3.0, air, POSCTL) == ACCEPTED and refusing.mode == POSCTL
    assert refusing.drain_events()[-1].text == "Pilot switched to POSCTL (RC)"


def test_silent_endpoint_sends_nothing_but_still_receives():
    gcs = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.bind(("127.0.0.1", 0))
    gcs.settimeout(0.2)
    endpoint = MavlinkEndpoint(gcs.getsockname()[1])
    try:
        endpoint.tx_silent = True
        endpoint.send(mavlink.MAVLink_heartbeat_message(2, 12, 0, 0, 0, 3))
        with pytest.raises(TimeoutError):
            gcs.recv(1024)
        assert endpoint.dropped_silent == 1
        packer = mavlink.MAVLink(None, srcSystem=1, srcComponent=195)
        gcs.sendto(mavlink.MAVLink_heartbeat_message(18, 8, 0, 0, 0, 3).pack(packer), ("127.0.0.1", endpoint.local_port))
        deadline = time.monotonic() + 2.0
        while not (received := endpoint.receive()) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert [m.get_type() for m in received] == ["HEARTBEAT"]
    finally:
        endpoint.close()
        gcs.close()


def test_stuck_vehicle_ignores_setpoints_from_its_time():
    faults = _faults("vehicle-stuck@2")
    assert not faults.stuck(T_OFFBOARD + 1.9)
    assert faults.stuck(T_OFFBOARD + 2.0) and faults.stuck(T_OFFBOARD + 5.0)
    assert faults.injected == {FaultKind.VEHICLE_STUCK: T_OFFBOARD + 2.0}
    assert not _faults("camera-stall@0").stuck(T_OFFBOARD + 5.0)
