"""Bota Systems F/T sensors through ``bota_driver`` (optional extra ``tergodic[bota]``)."""

from tergodic_cli.backends.bota.sensor import BotaConfig, BotaSensor

__all__ = ["BotaConfig", "BotaSensor"]
