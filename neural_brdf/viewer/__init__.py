"""What a person looks at: the run report, its plots and the interactive viewer.

* :mod:`.report`: ``report.html`` / ``report.md`` of a finished run folder.
* :mod:`.plots`: matplotlib figures (slices, lobes, albedo, Rusinkiewicz maps, renders).
* :mod:`.page`: the self-contained WebGL2 viewer page (``page.js``), ``neural-brdf view``.
"""
