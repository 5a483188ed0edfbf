"""The per-store query adapter of the learned view encoder.

A photo of an object does not look like a render of its model: other light, a camera's noise and blur, a
mask that cuts a little off. A store can learn that gap for its own models without any label beyond which
model it rendered:

* :mod:`pipeline.adapter.probes` makes *probe queries* from the store's own rendered views (no new
  rendering): each view's object, cut from the render's gray, scaled, pasted on a random background,
  maybe partly occluded and run through a camera's degradations, then cut out again the way a query cuts
  its ROI. The onboarding stage ``probe`` (:mod:`pipeline.onboard.stages.probe`) embeds a few per model with
  the learned view encoder's query path (table ``probe_embeddings``), incrementally like every stage.
* :mod:`pipeline.adapter.fit` fits a low-rank linear map ``q -> q (I + U W)`` of the ROI's learned vector
  with a softmax over the models' best-view cosines: the probe's own model against the others.
* :mod:`pipeline.adapter.table` keeps the fitted map in the store (table ``adapters``) with its provenance
  (the models and the encoder's and probes' fingerprints it was fitted on); an onboarding run that changed
  them refits it at its end. A query applies it only when the provenance matches what it reads.

The ranking uses the adapted cosine with its own fusion weights (``QuerySettings.adapter_fuse``); the
open-set verdict keeps reading the plain scores, which the calibration was fitted on (an adapter pulls an
absent object's ROI towards the library's models too). docs/results.md, section 11.
"""
