"""PolySfT: shape-from-template on image sequences with oriented n-jet patches.

A textured template (camera coordinates, the shape of the first frame) is deformed so that its
soft renders (:mod:`polygeo.render`) match every frame of a monocular video (thesis section 5.3).
The template is a PolyFit :class:`polygeo.patches.PatchSet` (by default the fewest patches that
are height graphs: one for a sheet, several for a tube or a cap); each frame has
jet-coefficient offsets, per-point ``uv`` displacements and a rigid motion, optimised with
Adam over an adaptive sliding window of frames. A per-vertex baseline (classical energy-based
SfT) shares the losses and the optimiser.

Modules
-------
``sft.data``      sequence format, validated lazy loader, atomic writer
``sft.template``  :class:`~sft.template.JetTemplate`: the template as oriented jet patches
``sft.model``     :class:`~sft.model.JetModel` (PolySfT), :class:`~sft.model.VertexModel`
                  (baseline), :func:`~sft.model.build_model`
``sft.losses``    colour + silhouette terms, inextensibility (eq. 47), temporal terms (eq. 48,
                  and a constant-velocity prior)
``sft.settings``  :class:`~sft.settings.SfTSettings` (model, optimiser, losses, raster, output)
``sft.window``    one window: objective, per-frame Adam, :func:`~sft.window.reconstruct_window`
``sft.optimize``  :func:`~sft.optimize.run_sft` (sliding window, re-partitioning, checkpoints,
                  resume)
``sft.metrics``   e_3D, e_n, RMSE
``sft.cli``       ``polygeo sft SEQUENCE -o OUT`` and the SfT part of ``polygeo demo``

Example
-------
>>> from sft.optimize import SfTSettings, run_sft  # doctest: +SKIP
>>> res = run_sft("data/bend", "out/bend", SfTSettings.from_flat(max_iterations=200))
>>> res.summary["e_3d"], res.summary["e_3d_template"]

Departures from the thesis (documented where they are set): parameters live in normalised
units (the patch radius is 1), which is what the thesis' learning rates are applied to;
``inextensibility_weight`` defaults to 10 rather than 0.1 and ``lr_rigid`` to 1e-3 rather
than 1e-4 for these units (see :mod:`sft.settings`); the soft coverage is remapped before
the silhouette and colour terms (see :meth:`sft.losses.ImageTerms.render`); the number of
patches is chosen from the template (``patches="auto"``) rather than fixed at one.
"""
