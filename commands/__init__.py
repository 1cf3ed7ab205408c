"""One thin module per verb: parse options, call the library, print. Installed as ``tergodic_cli.commands``."""
