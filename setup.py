"""Build of dvla's one optional C extension (dvla.fabric._views: the decoder's per-message span
check and array views). Everything else is in pyproject.toml. Without a C compiler the
extension is skipped and dvla runs the same decoder in Python."""

import numpy
from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "dvla.fabric._views",
            ["dvla/fabric/_views.c"],
            include_dirs=[numpy.get_include()],
            optional=True,
        )
    ]
)
