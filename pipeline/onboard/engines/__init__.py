"""Engines that run the onboarding stages: ``local`` (processes on this machine) and ``ray`` (Ray Data)."""
