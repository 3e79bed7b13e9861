"""The `telerobot` command and the zenoh-cli codec entry points.

The codec groups' names have a '-' that pyproject tables refuse.

zenoh-cli (PyPI) gathers codecs from `zenoh-cli.codecs.*`; some versions spell it
`zenoh_cli.codecs.*`, so both are registered. Everything else is in pyproject.toml.
"""

from setuptools import setup

_DECODER = ["telerobot = services.bus.zenoh_cli_codec:decode"]
_ENCODER = ["telerobot = services.bus.zenoh_cli_codec:encode"]

setup(
    entry_points={
        "console_scripts": ["telerobot = services.tools.cli.main:main"],
        "zenoh-cli.codecs.decoders": _DECODER,
        "zenoh-cli.codecs.encoders": _ENCODER,
        "zenoh_cli.codecs.decoders": _DECODER,
        "zenoh_cli.codecs.encoders": _ENCODER,
    }
)
