"""bridgeos: the command line of a bridgeOS cloud, over its REST API and /ws/client/ only."""

__version__ = "0.1.0"
