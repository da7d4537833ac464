"""Scene-building helper for the Blender tests that runs on every Blender the extension claims."""


def node_tree(idblock):
    """The node tree of a new material or world.

    Blender 5.0+ gives every new material and world a node tree; 4.5 gives
    none until ``use_nodes`` is switched on (the toggle is deprecated in 5.x).
    """
    if getattr(idblock, "node_tree", None) is None:
        idblock.use_nodes = True
    return idblock.node_tree
