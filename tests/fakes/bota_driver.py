"""A fake ``bota_driver`` module (bota-driver 1.1.16), shaped like the real binding.

Observed on the real package (its 'Bota_Dummy' interface) and copied here: the constructor takes a
JSON path (RuntimeError "Failed to open configuration file: ..." when missing) or a BotaDriverConfig
(ValueError when product_name is empty); states UNCONFIGURED -> configure() -> INACTIVE -> activate()
-> ACTIVE -> deactivate() -> INACTIVE -> shutdown() -> FINALIZED; tare() returns False unless INACTIVE;
read_frame() returns an all-zero frame with timestamp 0 when no new sample has arrived;
read_frame_blocking() returns the latest sample; timestamps are a uint32 microsecond counter.

Samples come from the attached :class:`fakes.world.FakeWorld` (``_WORLD``), at the world's time
quantised to the sensor period; the counter starts just before its wrap-around, so a run crosses it.
"""

from __future__ import annotations

import enum
import os

import numpy as np

__version__ = "1.1.16-fake"
_WORLD = None
PERIOD_US = 1000
_TIMESTAMP_OFFSET_US = 2**32 - 700_000  # wraps 0.7 s into a run


class DriverState(enum.Enum):
    INITIAL = 0
    UNCONFIGURED = 1
    INACTIVE = 2
    ACTIVE = 3
    FINALIZED = 4
    TERMINAL = 5
    CONFIGURING = 6
    CLEANINGUP = 7
    SHUTTING_DOWN = 8
    ACTIVATING = 9
    DEACTIVATING = 10
    ERROR_PROCESSING = 11


class DataStatus:
    def __init__(self, invalid: int = 0, overrange: int = 0):
        self.val = 1 if (invalid or overrange) else 0
        self.invalid = int(invalid)
        self.overrange = int(overrange)
        self.raw = 0
        self.throttled = 0


class BotaFrame:
    def __init__(self, timestamp: int = 0, wrench=None, status: DataStatus | None = None):
        w = np.zeros(6) if wrench is None else np.asarray(wrench, dtype=float)
        self.force = [float(x) for x in w[:3]]
        self.torque = [float(x) for x in w[3:]]
        self.timestamp = int(timestamp)
        self.status = status or DataStatus()
        self.temperature = 25.0
        self.acceleration = [0.0, 0.0, 0.0]
        self.angular_rate = [0.0, 0.0, 0.0]


class BotaDummyCommunicationInterfaceConfig:
    pass


class BotaBinaryCommunicationInterfaceConfig:
    def __init__(self):
        self.com_port = ""
        self.baudrate = 460800


class BotaSocketCommunicationInterfaceConfig:
    def __init__(self):
        self.sensor_ip_address = ""


class GenASensorOperationConfig:
    def __init__(self):
        self.app_mode = None
        self.app_submode = None
        self.wrench_offset = None
        self.temperature_coefficients = None


class DriverOperationConfig:
    def __init__(self):
        self.runtime_verbosity = True
        self.register_with_daemon = False
        self.skip_metadata_reading = False


class BotaDriverConfig:
    def __init__(self):
        self.product_name = ""
        self.serial_number = ""
        self.communication_interface_name = ""
        self.is_mn1s = None
        self.binary_communication_interface_params = None
        self.socket_communication_interface_params = None
        self.coe_communication_interface_params = None
        self.can_communication_interface_params = None
        self.dummy_communication_interface_params = None
        self.gen0_sensor_operation_params = None
        self.genA_sensor_operation_params = None
        self.driver_operation_params = DriverOperationConfig()


class BotaDriver:
    def __init__(self, config):
        if isinstance(config, str):
            if not os.path.isfile(config):
                raise RuntimeError(f"Failed to open configuration file: {config}")
        elif isinstance(config, BotaDriverConfig):
            if not config.product_name:
                raise ValueError("BotaDriverConfig: product_name must not be empty")
            if not config.serial_number:
                raise ValueError("BotaDriverConfig: serial_number must not be empty")
            if config.communication_interface_name == "Bota_Dummy" and config.dummy_communication_interface_params is None:
                raise ValueError("BotaDriverConfig: 'Bota_Dummy' needs dummy_communication_interface_params")
            if config.genA_sensor_operation_params is None and config.gen0_sensor_operation_params is None:
                raise ValueError("BotaDriverConfig: a sensor operation config is mandatory")
        else:
            raise TypeError("__init__(): incompatible constructor arguments")
        self._state = DriverState.UNCONFIGURED
        self._last_read = None
        self._world = _WORLD
        self.hardware_tares = 0

    def get_driver_state(self) -> DriverState:
        return self._state

    def get_driver_version_string(self) -> str:
        return __version__

    def get_expected_timestep_us(self) -> int:
        return PERIOD_US

    def configure(self) -> bool:
        if self._state != DriverState.UNCONFIGURED or self._world is None:
            return False
        self._state = DriverState.INACTIVE
        return True

    def activate(self) -> bool:
        if self._state != DriverState.INACTIVE:
            return False
        self._state = DriverState.ACTIVE
        return True

    def deactivate(self) -> bool:
        if self._state != DriverState.ACTIVE:
            return False
        self._state = DriverState.INACTIVE
        return True

    def shutdown(self) -> bool:
        self._state = DriverState.FINALIZED
        return True

    def cleanup(self) -> bool:
        self._state = DriverState.UNCONFIGURED
        return True

    def tare(self) -> bool:
        if self._state != DriverState.INACTIVE:
            return False  # "Tare can only be called in INACTIVE state"
        self.hardware_tares += 1
        return True

    def _sample(self) -> BotaFrame:
        w = self._world
        tick = int(w.t * 1e6) // PERIOD_US
        ts = (tick * PERIOD_US + _TIMESTAMP_OFFSET_US) % 2**32
        wrench = w.sensor_wrench()
        status = DataStatus(invalid=int(not np.all(np.isfinite(wrench))))
        return BotaFrame(ts, np.nan_to_num(wrench), status), tick

    def read_frame(self) -> BotaFrame:
        if self._state != DriverState.ACTIVE:
            return BotaFrame()
        frame, tick = self._sample()
        if tick == self._last_read:
            return BotaFrame()  # "Data buffer is empty"
        self._last_read = tick
        return frame

    def read_frame_blocking(self) -> BotaFrame:
        if self._state != DriverState.ACTIVE:
            return BotaFrame()
        if self._world.sensor_fault == "freeze" and getattr(self, "_last_frame", None) is not None:
            return self._last_frame  # the stream stopped: the same sample again
        frame, tick = self._sample()
        self._last_read, self._last_frame = tick, frame
        return frame
