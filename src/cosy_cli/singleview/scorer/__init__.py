"""The learned hypothesis scorer (``cosy train scorer``, ``cosy estimate --scorer FILE``).

It joins the training-free verification (:mod:`~cosy_cli.singleview.training_free.verify`):
:meth:`~cosy_cli.singleview.training_free.verify.Verifier.score` renders every hypothesis into the
detection's 64 px crop anyway; with a scorer, those renders, the observed crop and the
training-free score terms go through a network (:mod:`.model`: a small CNN from scratch, arch
"plain", or a head on frozen ImageNet maps of EfficientNet-Lite0, arch "lite0") that predicts how
much of the BOP recall the hypothesis earns (:func:`cosy_cli.training.scorer_target.ar_contribution`:
the fraction of the MSSD and MSPD thresholds it meets). With the estimate setting ``scorer_scope``
"all" the prediction replaces the hand-weighted sum wherever that sum was used: the ranking of the
template hypotheses, the accept test of the contour alignment and of the local search, the image
term of the depth pick; with "rank" it only orders each detection's final hypotheses.

:mod:`.features` builds the network's inputs from what the verifier already has (no extra render);
:mod:`.runtime` runs the exported ONNX file. Training lives in :mod:`cosy_cli.training.scorer`
(data: :mod:`cosy_cli.training.scorer_data`).
"""
