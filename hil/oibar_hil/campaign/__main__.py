import sys

from oibar_hil.campaign.cli import main

sys.exit(main())
