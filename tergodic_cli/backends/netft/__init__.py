"""ATI Net F/T sensors over raw UDP (RDT protocol, standard library only: no extra needed)."""

from tergodic_cli.backends.netft.sensor import NetFTConfig, NetFTSensor, fetch_calibration

__all__ = ["NetFTConfig", "NetFTSensor", "fetch_calibration"]
