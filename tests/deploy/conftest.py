"""The deployed stack, shared by every test module here."""

from tests.deploy.deployed import stack

__all__ = ["stack"]
