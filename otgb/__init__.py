"""otgb: completing incomplete physics models from unpaired data with kernel weak OT."""

__version__ = "0.1.0"
