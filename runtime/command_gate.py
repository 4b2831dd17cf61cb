"""The one door every setpoint and mode command goes through.

The policy task and the watchdog both command the vehicle.  The gate serialises them (a policy
setpoint can never land after the watchdog's hover) and enforces the watchdog's decisions: once
closed, policy setpoints are dropped; once released (the pilot took over), nothing is sent at all.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Protocol

from .contract import HOVER, VelocityBodyYawspeed

log = logging.getLogger(__name__)


class CommandedVehicle(Protocol):
    """What the gate needs from the vehicle (``runtime.vehicle.Vehicle`` implements it)."""

    async def set_velocity_body(self, cmd: VelocityBodyYawspeed) -> None: ...

    async def stop_offboard(self) -> None: ...


class CommandGate:
    """Serialises commands; closed to the policy until :meth:`open_for_policy`."""

    def __init__(self, vehicle: CommandedVehicle) -> None:
        self._vehicle = vehicle
        self._lock = asyncio.Lock()
        self._policy_open = False
        self._released = False

    @property
    def policy_open(self) -> bool:
        return self._policy_open and not self._released

    @property
    def released(self) -> bool:
        """True once the pilot took over: the runtime sends nothing more."""
        return self._released

    def open_for_policy(self) -> None:
        """Let policy setpoints through (offboard entered, supervision started)."""
        self._policy_open = True
        self._released = False

    async def send_policy(self, cmd: VelocityBodyYawspeed) -> bool:
        """Send a policy setpoint; False (and nothing sent) if the gate is closed."""
        async with self._lock:
            if not self.policy_open:
                return False
            await self._vehicle.set_velocity_body(cmd)
            return True

    async def hover(self) -> bool:
        """Close the gate to the policy and send a zero-velocity setpoint; False if released."""
        return await self.send_own(HOVER)

    async def send_own(self, setpoint: VelocityBodyYawspeed) -> bool:
        """Close the gate to the policy and send the runtime's own ``setpoint`` (the brake's, the
        retreat's); False if released."""
        self._policy_open = False
        async with self._lock:
            if self._released:
                return False
            await self._vehicle.set_velocity_body(setpoint)
            return True

    async def hold(self) -> bool:
        """Close the gate to the policy and leave offboard into Hold; False if released."""
        self._policy_open = False
        async with self._lock:
            if self._released:
                return False
            await self._vehicle.stop_offboard()
            return True

    def release(self) -> None:
        """The pilot took over: send nothing from now on (takes effect at once, no await)."""
        self._policy_open = False
        self._released = True
        log.warning("command gate released: the runtime sends no more setpoints or mode changes")
