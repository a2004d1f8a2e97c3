"""The accuracy report: figures measured on the fused clouds, drawn into a PDF and metrics.json.

Module map: ``metrics`` (gauge block, plane, sphere and freeform measured in a cloud),
``pages`` (the report's pages, drawn with matplotlib), ``accuracy`` (the ``report`` stage:
every figure measured, checked against its tolerance and written twice), ``nominal`` (a
freeform scan against its CAD mesh; its parts ``nominal_surface``, ``nominal_align``,
``nominal_regions``, ``nominal_map``).
"""
