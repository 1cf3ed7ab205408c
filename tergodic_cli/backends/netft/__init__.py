"""ATI Net F/T sensors over raw UDP (RDT protocol, standard library only: no extra needed)."""

from tergodic_cli.backends.netft.sensor import NetFTConfig, NetFTSensor, fetch_calibration



def make_sensor(cfg: NetFTConfig, arm=None) -> NetFTSensor:
    """The registry's factory (backends/registry.py): a Net F/T sensor, not yet connected."""
    return NetFTSensor(cfg)


__all__ = ["NetFTConfig", "NetFTSensor", "fetch_calibration", "make_sensor"]
