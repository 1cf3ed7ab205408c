import sys

from tergodic_cli.cli import main

sys.exit(main())
