"""Finding the plate and the display content: the optimizer, its memory budget and the per-frame
display solve of a tracked design.
"""
