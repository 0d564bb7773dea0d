"""Drawing what `aperture_fab.validation` judged: a `Report`'s figures, the HTML report page
and views.npz (`evidence.assemble`), and the assembly sheet of a design. Nothing here judges a
part; every figure and verdict drawn comes from validation's values.
"""
