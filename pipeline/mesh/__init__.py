"""Mesh code shared by onboarding, query and evaluation: find and hash files (``discover``), load and
normalise meshes (``load``), place cameras (``cameras``) and render views (``render``, settings in
``settings``). Nothing here knows about the store or the onboarding stages."""
