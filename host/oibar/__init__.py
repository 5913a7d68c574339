"""OIBAR companion-computer software.

The package is split so that the link (``oibar.link``) can be used on its own by the
navigation pipeline, the HIL rig and the command-line tool (``oibar.cli``).
"""

__version__ = "0.1.0"
