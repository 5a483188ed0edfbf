"""Build glue that pyproject.toml cannot express: ``sql/`` stays at the top of the repo (the design card's
layout) and ships inside the package as ``pipeline/_sql``, read through ``importlib.resources``.

Everything else (metadata, dependencies, the ``oscar`` script) is in ``pyproject.toml``.
"""

from setuptools import find_packages, setup

setup(
    packages=find_packages(include=["pipeline", "pipeline.*"]) + ["pipeline._sql"],
    package_dir={"pipeline._sql": "sql"},
    package_data={"pipeline": ["py.typed", "serve/static/*", "query/calibration/*.json"], "pipeline._sql": ["**/*.sql"]},
    include_package_data=False,
)
