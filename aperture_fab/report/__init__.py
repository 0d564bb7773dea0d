"""Drawing what `aperture_fab.validation` judged: report.json's blocks, views.npz and the HTML
report page with its figures (`evidence.assemble`), and the assembly sheet of a design. Nothing
here judges a part; every figure and verdict drawn comes from validation's values.
"""
