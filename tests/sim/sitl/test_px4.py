"""PX4 custom modes: HEARTBEAT encoding main << 16 | sub << 24 and DO_SET_MODE decoding."""

import pytest

from sim.sitl.px4 import HOLD, LAND, OFFBOARD, POSCTL, TAKEOFF, AutoSubMode, MainMode, Px4Mode, UnknownModeError


def test_known_encodings():
    assert OFFBOARD.custom_mode == 6 << 16 == 393216
    assert HOLD.custom_mode == (4 << 16) | (3 << 24) == 50593792
    assert TAKEOFF.custom_mode == (4 << 16) | (2 << 24)
    assert LAND.custom_mode == (4 << 16) | (6 << 24)
    assert POSCTL.custom_mode == 3 << 16


def test_names_follow_mavsdk():
    assert [m.name for m in (HOLD, TAKEOFF, LAND, OFFBOARD, POSCTL)] == ["HOLD", "TAKEOFF", "LAND", "OFFBOARD", "POSCTL"]
    assert Px4Mode(MainMode.AUTO, AutoSubMode.RTL).name == "RETURN_TO_LAUNCH"


@pytest.mark.parametrize("main", list(MainMode))
def test_round_trip_every_mode(main):
    subs = list(AutoSubMode) if main == MainMode.AUTO else [0]
    for sub in subs:
        mode = Px4Mode.from_main_sub(main, sub)
        assert Px4Mode.from_custom_mode(mode.custom_mode) == mode


def test_non_auto_ignores_sub_mode():
    assert Px4Mode.from_main_sub(6, 3) == OFFBOARD


@pytest.mark.parametrize("main, sub", [(0, 0), (8, 0), (4, 0), (4, 9)])
def test_unknown_modes_raise(main, sub):
    with pytest.raises(UnknownModeError):
        Px4Mode.from_main_sub(main, sub)
