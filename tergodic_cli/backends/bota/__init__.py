"""Bota Systems F/T sensors through bota_driver (``--ft bota``, ``pip install 'tergodic[bota]'``)."""

from tergodic_cli.backends.bota.sensor import WRAP_US, BotaConfig, BotaSensor


def make_sensor(cfg: BotaConfig, arm=None) -> BotaSensor:
    """The registry's factory (backends/registry.py): a Bota sensor, not yet connected."""
    return BotaSensor(cfg)


__all__ = ["WRAP_US", "BotaConfig", "BotaSensor", "make_sensor"]
