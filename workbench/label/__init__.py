"""Ground-truth labelling: one frame's labels (``frame``: snap, fit, save and load in scene_gt form), and a whole
sequence's (``sequence``: one world pose per still object carried to every frame, ``check``: each frame's labels
against its depth, ``multiview``: fitting a label to all frames at once, ``run``: ``workbench label``)."""
