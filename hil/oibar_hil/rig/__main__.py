import sys

from oibar_hil.rig.cli import main

sys.exit(main())
