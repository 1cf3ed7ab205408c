"""Bota Systems F/T sensors through Bota's driver (``pip install 'tergodic[bota]'``, module ``bota_driver``).

bota-driver 1.1.16: ``BotaDriver(config)``, then ``configure() -> activate() -> read_frame_blocking() ...
-> deactivate() -> shutdown()``. The non-blocking read returns an all-zero frame when no sample is new
(a zero wrench would look like "no contact"), and the driver's ``tare()`` works only while inactive, so
this backend reads blocking and tares in software (docs/hardware.md, "Bota"). A frame flagged invalid
or over-range reads as NaN, which the safety guard turns into a hold.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tergodic_cli.errors import TergodicError, require
from tergodic_cli.backends.extras import import_sdk, one_line
from tergodic_cli.robot.interfaces import WrenchSensor

WRAP_US = 2**32


@dataclass
class BotaConfig:
    """address : path of the sensor's JSON driver configuration (Bota's documented set-up), or
    "dummy" for the driver's built-in simulated sensor. frame_in_ee : (4, 4) sensor frame in the TCP
    frame (measure it on your mounting). tare_samples : frames averaged by :meth:`BotaSensor.tare`."""

    address: str
    frame_in_ee: np.ndarray | None = None
    tare_samples: int = 50

    def validate(self) -> None:
        a = str(self.address or "")
        require(a == "dummy" or a.lower().endswith(".json"),
                f"--ft-address '{a}' is not a Bota driver configuration",
                "give the path of the sensor's JSON configuration file (see Bota's driver documentation), or 'dummy'")
        if a != "dummy":
            require(Path(a).is_file(), f"the Bota configuration {a} does not exist", "check the path given to --ft-address")
        require(int(self.tare_samples) >= 1, "tare_samples must be >= 1", "e.g. 50")


class BotaSensor(WrenchSensor):
    """A Bota sensor behind :class:`~tergodic_cli.robot.interfaces.WrenchSensor`.

    ``read()`` returns the latest frame's wrench minus the tare offset, with t = the sensor's
    timestamp in seconds (unwrapped); ``tare()`` averages ``tare_samples`` frames, the tool free.
    """

    bad_tare = ("the Bota sensor flagged samples invalid or over range while taring",
                "keep the tool free and still, check the sensor, and retry")

    def __init__(self, cfg: BotaConfig):
        cfg.validate()
        super().__init__(cfg.frame_in_ee, cfg.tare_samples)
        self.cfg = cfg
        self.driver = None
        self._last_us: int | None = None
        self._wraps = 0

    @property
    def is_connected(self) -> bool:
        return self.driver is not None

    def connect(self) -> None:
        if self.driver is not None:
            return
        bd = import_sdk("bota_driver")
        try:
            driver = bd.BotaDriver(self._driver_config(bd))
        except Exception as exc:
            raise TergodicError(f"the Bota driver rejected its configuration: {one_line(exc)}",
                                "check the JSON configuration (interface, port, serial number)") from None
        if not driver.configure():
            raise TergodicError("the Bota sensor could not be configured", "check the cable, the port in the configuration and its permissions")
        if not driver.activate():
            driver.shutdown()
            raise TergodicError("the Bota sensor did not start streaming", "power-cycle the sensor and retry")
        self.driver = driver

    def _driver_config(self, bd):
        if self.cfg.address != "dummy":
            return str(self.cfg.address)
        cfg = bd.BotaDriverConfig()
        cfg.product_name, cfg.serial_number = "PRT-SENS-IND-PS", "DUMMY"  # the driver refuses empty names
        cfg.communication_interface_name = "Bota_Dummy"
        cfg.dummy_communication_interface_params = bd.BotaDummyCommunicationInterfaceConfig()
        op = bd.GenASensorOperationConfig()
        op.app_mode, op.app_submode = 2, 7  # the driver's documented example values
        cfg.genA_sensor_operation_params = op
        return cfg

    def _sample(self) -> tuple[float, np.ndarray]:
        require(self.driver is not None, "the Bota sensor is not connected", "call connect() first")
        fr = self.driver.read_frame_blocking()
        us = int(fr.timestamp)
        if self._last_us is not None and self._last_us - us > WRAP_US // 2:
            self._wraps += 1
        self._last_us = us
        w = np.array(list(fr.force) + list(fr.torque), dtype=float)
        if int(fr.status.invalid) or int(fr.status.overrange) or w.shape != (6,):
            w = np.full(6, np.nan)
        return 1e-6 * (us + self._wraps * WRAP_US), w

    def disconnect(self) -> None:
        if self.driver is None:
            return
        try:
            self.driver.deactivate()
            self.driver.shutdown()
        finally:
            self.driver = None

