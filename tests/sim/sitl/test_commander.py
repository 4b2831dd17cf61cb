"""PX4's commander rules, with hand-made states and times (no process, no physics)."""

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from runtime.contract.frames import quat_from_euler
from sim.sitl.commander import ACCEPTED, DENIED, TEMPORARILY_REJECTED, Commander
from sim.sitl.kinematics import Kinematics
from sim.sitl.params import INT32, OBL_HOLD, OBL_LAND, OBL_POSITION, OBL_RETURN, OBL_TERMINATE, Param, ParamError, ParamTable
from sim.sitl.px4 import HOLD, LAND, OFFBOARD, POSCTL, RETURN, TAKEOFF, MainMode, Px4Mode
from sim.sitl.setpoints import OffboardSetpoint, Sticks

HOME = np.array([1.0, 3.0, 0.15])
TAKEOFF_ALT_M = 1.5


def kin(z=0.15, vel=(0.0, 0.0, 0.0), yaw=0.0, on_ground=None, x=1.0, y=3.0) -> Kinematics:
    return Kinematics(
        t_ns=0,
        pos_enu_m=np.array([x, y, z]),
        vel_enu_m_s=np.array(vel, dtype=float),
        quat_enu_flu=quat_from_euler(0.0, 0.0, yaw),
        angvel_body_flu_rad_s=np.zeros(3),
        on_ground=(z <= 0.15) if on_ground is None else on_ground,
    )


def hover_setpoint(t_s: float, vel=(0.0, 0.0, 0.0), yaw_rate=0.0) -> OffboardSetpoint:
    return OffboardSetpoint(t_s, np.array(vel, dtype=float), yaw_rate, None)


@pytest.fixture
def commander() -> Commander:
    return Commander(ParamTable(takeoff_alt_m=TAKEOFF_ALT_M), HOME, kin(), 0.0)


def flying(commander: Commander, t_s: float = 1.0) -> Kinematics:
    """Armed, taken off and holding at the take-off altitude."""
    assert commander.arm(0.0, kin()) == ACCEPTED
    assert commander.takeoff(0.0, kin(), None) == ACCEPTED
    air = kin(z=HOME[2] + TAKEOFF_ALT_M)
    commander.update(t_s, air)
    assert commander.mode == HOLD
    return air


def test_boots_disarmed_in_hold_on_the_ground(commander):
    assert not commander.armed and commander.mode == HOLD and commander.armable
    assert commander.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
    assert commander.mode_log == [(0.0, "HOLD")]


def test_arming_rules(commander):
    assert commander.arm(0.0, kin(z=2.0)) == DENIED  # not landed
    assert commander.arm(0.0, kin()) == ACCEPTED
    assert commander.arm(0.1, kin()) == ACCEPTED  # already armed
    texts = [e.text for e in commander.drain_events()]
    assert texts == ["Arming denied: not landed", "Armed by external command"]
    commander.crash(1.0, "wall")
    assert not commander.armed and not commander.armable
    assert commander.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND
    assert commander.arm(2.0, kin()) == DENIED


def test_disarm_in_air_needs_force(commander):
    air = flying(commander)
    assert commander.disarm(2.0, air, force=False) == DENIED and commander.armed
    assert commander.disarm(2.0, air, force=True) == ACCEPTED and not commander.armed


def test_takeoff_climbs_then_holds_at_the_takeoff_altitude(commander):
    assert commander.takeoff(0.0, kin(), None) == DENIED  # disarmed
    commander.arm(0.0, kin())
    assert commander.takeoff(0.0, kin(), None) == ACCEPTED and commander.mode == TAKEOFF
    climbing = kin(z=0.8, on_ground=False)
    commander.update(0.5, climbing)
    assert commander.landed_state == mavlink.MAV_LANDED_STATE_TAKEOFF
    cmd = commander.velocity_command(0.5, climbing)
    assert cmd.vel_enu_m_s[2] > 0.5 and abs(cmd.vel_enu_m_s[0]) < 1e-9
    commander.update(1.0, kin(z=HOME[2] + TAKEOFF_ALT_M - 0.85))
    assert commander.mode == TAKEOFF
    # As PX4 v1.16 (NAV_MC_ALT_RAD, 0.8 m): complete within 0.8 m of the height, Hold climbs on.
    commander.update(1.5, kin(z=HOME[2] + TAKEOFF_ALT_M - 0.75))
    assert commander.mode == HOLD and commander.landed_state == mavlink.MAV_LANDED_STATE_IN_AIR
    assert [m for _, m in commander.mode_log] == ["HOLD", "TAKEOFF", "HOLD"]
    # Hold targets the take-off point itself.
    below = kin(z=HOME[2] + TAKEOFF_ALT_M - 0.3)
    assert commander.velocity_command(2.0, below).vel_enu_m_s[2] == pytest.approx(0.3)


def test_offboard_entry_rules(commander):
    assert commander.set_mode(0.0, kin(), OFFBOARD) == DENIED  # disarmed
    air = flying(commander)
    assert commander.set_mode(2.0, air, OFFBOARD) == TEMPORARILY_REJECTED  # no setpoint yet
    commander.on_setpoint(hover_setpoint(2.0))
    assert commander.set_mode(2.6, air, OFFBOARD) == TEMPORARILY_REJECTED  # setpoint 0.6 s old
    commander.on_setpoint(hover_setpoint(2.7))
    assert commander.set_mode(2.8, air, OFFBOARD) == ACCEPTED and commander.mode == OFFBOARD


def test_offboard_follows_the_setpoint(commander):
    air = flying(commander)
    commander.on_setpoint(hover_setpoint(2.0, vel=(1.0, -0.5, 0.2), yaw_rate=0.3))
    commander.set_mode(2.0, air, OFFBOARD)
    cmd = commander.velocity_command(2.1, air)
    np.testing.assert_allclose(cmd.vel_enu_m_s, [1.0, -0.5, 0.2])
    assert cmd.yaw_rate_enu_rad_s == 0.3


def _lose_offboard(commander: Commander, action: int | None = None) -> Kinematics:
    """Fly in OFFBOARD with the last setpoint at t = 2.0 s, COM_OBL_RC_ACT = ``action`` (None: PX4's default)."""
    if action is not None:
        commander._params.set_from_wire("COM_OBL_RC_ACT", ParamTable.wire_value(Param("COM_OBL_RC_ACT", action, INT32)), INT32)
    air = flying(commander)
    commander.on_setpoint(hover_setpoint(2.0))
    commander.set_mode(2.0, air, OFFBOARD)
    commander.drain_events()
    commander.update(2.99, air)
    assert commander.mode == OFFBOARD  # not before COM_OF_LOSS_T = 1 s
    commander.update(3.01, air)
    return air


def test_offboard_loss_by_default_is_position_mode_which_lands_without_rc(commander):
    """PX4's default COM_OBL_RC_ACT = 0: Position mode, which without RC sticks cannot run, so the
    vehicle descends where it is (PX4: "Matching flight task was not able to run" -> landing)."""
    air = _lose_offboard(commander)
    assert commander.mode == POSCTL
    (event,) = commander.drain_events()
    assert event.severity == mavlink.MAV_SEVERITY_WARNING and "offboard lost" in event.text and "no RC" in event.text
    cmd = commander.velocity_command(3.1, air)
    assert cmd.vel_enu_m_s[2] == pytest.approx(-commander._params["MPC_LAND_SPEED"])


def test_offboard_loss_in_position_mode_with_rc_holds_on_the_sticks(commander):
    commander.on_sticks(Sticks(2.9, 0.0, 0.0, 0.0, 0.0))
    air = _lose_offboard(commander)
    assert commander.mode == POSCTL
    np.testing.assert_allclose(commander.velocity_command(3.05, air).vel_enu_m_s, 0.0, atol=1e-9)  # brakes, no descent


@pytest.mark.parametrize("action, mode", [(OBL_HOLD, HOLD), (OBL_LAND, LAND), (OBL_RETURN, RETURN)])
def test_offboard_loss_follows_com_obl_rc_act(commander, action, mode):
    air = _lose_offboard(commander, action)
    assert commander.mode == mode and commander.armed
    (event,) = commander.drain_events()
    assert "offboard lost" in event.text and "no RC" not in event.text
    cmd = commander.velocity_command(3.1, air)
    if mode == HOLD:
        np.testing.assert_allclose(cmd.vel_enu_m_s, 0.0, atol=1e-9)
    elif mode == LAND:
        assert cmd.vel_enu_m_s[2] < 0.0
    else:  # Return: home at the current height, then Land there
        away = kin(z=air.pos_enu_m[2], x=HOME[0] + 2.0)
        cmd = commander.velocity_command(3.2, away)
        assert cmd.vel_enu_m_s[0] < 0.0 and cmd.vel_enu_m_s[2] == pytest.approx(0.0, abs=1e-9)
        commander.update(5.0, kin(z=air.pos_enu_m[2], x=HOME[0] + 0.1))
        assert commander.mode == LAND


def test_offboard_loss_with_terminate_stops_the_motors(commander):
    _lose_offboard(commander, OBL_TERMINATE)
    assert not commander.armed


def test_com_obl_rc_act_accepts_only_px4_values():
    params = ParamTable(takeoff_alt_m=1.0)
    with pytest.raises(ParamError, match="COM_OBL_RC_ACT=9 is not one of"):
        params.set_from_wire("COM_OBL_RC_ACT", ParamTable.wire_value(Param("COM_OBL_RC_ACT", 9, INT32)), INT32)
    assert params["COM_OBL_RC_ACT"] == OBL_POSITION


def test_hold_brakes_to_a_stop_then_holds_where_it_stopped(commander):
    air = flying(commander)
    moving = kin(z=air.pos_enu_m[2], vel=(1.5, 0.0, 0.0))
    commander.on_setpoint(hover_setpoint(2.0, vel=(1.5, 0.0, 0.0)))
    commander.set_mode(2.0, moving, OFFBOARD)
    commander.set_mode(2.1, moving, HOLD)
    np.testing.assert_allclose(commander.velocity_command(2.1, moving).vel_enu_m_s, 0.0, atol=1e-9)  # brake
    stopped = kin(z=air.pos_enu_m[2], vel=(0.05, 0.0, 0.0), x=2.0)  # came to rest 1 m further on
    commander.velocity_command(2.6, stopped)
    drifted = kin(z=air.pos_enu_m[2], x=2.2)
    cmd = commander.velocity_command(3.0, drifted)
    assert cmd.vel_enu_m_s[0] == pytest.approx(-0.2)  # holds where it stopped, not where Hold began


def test_land_descends_then_auto_disarms(commander):
    air = flying(commander)
    assert commander.land(2.0, air) == ACCEPTED and commander.mode == LAND
    commander.update(2.1, air)
    assert commander.landed_state == mavlink.MAV_LANDED_STATE_LANDING
    assert commander.velocity_command(2.1, air).vel_enu_m_s[2] == pytest.approx(-0.7)
    commander.update(5.0, kin())  # touch-down
    commander.update(6.9, kin())
    assert commander.armed
    commander.update(7.01, kin())  # COM_DISARM_LAND = 2 s
    assert not commander.armed
    assert [e.text for e in commander.drain_events()][-2:] == ["Landing detected", "Disarmed by landing"]


def test_armed_without_takeoff_disarms_after_com_disarm_prflt(commander):
    commander.arm(0.0, kin())
    commander.update(9.9, kin())
    assert commander.armed
    commander.update(10.1, kin())
    assert not commander.armed


def test_position_mode_flies_sticks_and_holds_when_centred(commander):
    air = flying(commander)
    assert commander.set_mode(2.0, air, POSCTL) == ACCEPTED
    yawed = kin(z=air.pos_enu_m[2], yaw=math.pi / 2)  # facing north
    commander.on_sticks(Sticks(2.0, forward=0.5, right=0.0, up=0.0, yaw_right=0.0))
    cmd = commander.velocity_command(2.0, yawed)
    np.testing.assert_allclose(cmd.vel_enu_m_s, [0.0, 1.0, 0.0], atol=1e-9)
    commander.on_sticks(Sticks(2.1, 0.0, 0.0, 0.0, 0.0))
    cmd = commander.velocity_command(2.1, yawed)
    np.testing.assert_allclose(cmd.vel_enu_m_s, 0.0, atol=1e-9)
    # Stale sticks (no MANUAL_CONTROL for > 0.5 s) count as centred.
    commander.on_sticks(Sticks(3.0, 1.0, 0.0, 0.0, 0.0))
    np.testing.assert_allclose(commander.velocity_command(3.6, yawed).vel_enu_m_s, 0.0, atol=1e-9)


def test_modes_it_cannot_fly_are_refused(commander):
    assert commander.set_mode(0.0, kin(), Px4Mode(MainMode.STABILIZED)) == DENIED
    assert commander.mode == HOLD
