"""The onboarding wing: ``python -m pipeline.onboard`` (``cli``), its configuration and fingerprints
(``config``), the planner (``plan``), the stages (``stages/``) and the engines that run them
(``engines/``: local and Ray). Heavy modules are imported by the code that needs them, so this package
stays light to import."""
