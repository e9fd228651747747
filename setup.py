"""Build of dvla's one optional C extension (dvla.fabric._views: the decoder's per-message fast
path). Everything else is in pyproject.toml. Without a C compiler, or without numpy in the
build environment (``--no-build-isolation``), the extension is skipped and dvla runs the same
decoder in Python."""

from setuptools import Extension, setup

try:
    import numpy
except ImportError:  # only possible without build isolation: pyproject.toml requires numpy
    numpy = None

setup(
    ext_modules=[] if numpy is None else [
        Extension(
            "dvla.fabric._views",
            ["dvla/fabric/_views.c"],
            include_dirs=[numpy.get_include()],
            optional=True,
        )
    ]
)
