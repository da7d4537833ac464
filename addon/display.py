"""How splat objects are drawn where Blender cannot draw Gaussian splats itself.

Before Blender 5.3 a point cloud has no splat drawing, so every splat object
gets a Geometry Nodes modifier (``MODIFIER_NAME``) that derives, at
evaluation time and from the splat attributes (``splat_layout``):

- a point radius of twice the geometric-mean standard deviation of ``scale``;
- ``splat_color``: the SH degree-0 colour ``0.5 + C0 * f_dc`` clipped to
  [0, 1] and converted from sRGB to linear, with alpha = the splat's opacity,
  drawn by the emissive material ``POINT_MATERIAL`` (Material Preview, EEVEE
  and Cycles; the view-dependent SH bands are not shown).

Its *Ellipsoids* input instead instances a sphere on every splat, rotated by
``rotation`` and scaled to ``ELLIPSOID_SIGMAS`` standard deviations, for close
inspection; on 5.3 and later the modifier exists only while that is on, since
Blender draws the splats itself. The modifier reads the attributes each time
it evaluates, so edits show at once, and it adds nothing to the data-block
that export reads.
"""

from __future__ import annotations

import bpy

from mlx3d.splatting import C0

from .splat_layout import current

MODIFIER_NAME = "MLX3D Splat Display"
TREE_NAME = "MLX3D Splat Display"
TREE_VERSION = 1
POINT_MATERIAL = "MLX3D Splat"
ELLIPSOID_MATERIAL = "MLX3D Splat Ellipsoid"
ELLIPSOID_SIGMAS = 2.0
ELLIPSOIDS = "Ellipsoids"
# the earlier add-on's ellipsoid modifier, replaced when a file is opened
LEGACY_MODIFIER = "MLX3D Ellipsoids"


def node_material(name: str, build):
    """The material ``name`` (reused when it exists), else a new one whose
    emptied node tree ``build(nodes, links)`` fills."""
    mat = bpy.data.materials.get(name)
    if mat is None:
        mat = bpy.data.materials.new(name)
        if bpy.app.version < (5, 0, 0):  # 5.0+ materials always use nodes
            mat.use_nodes = True
        mat.node_tree.nodes.clear()
        build(mat.node_tree.nodes, mat.node_tree.links)
    return mat


def attribute_material(name: str, attribute_type: str = "GEOMETRY", transparent: bool = True, attribute: str = "splat_color"):
    """An emissive material coloured by the colour attribute ``attribute`` (reused when it exists).

    attribute_type: where the shader reads the attribute ('GEOMETRY' for the
    points themselves, 'INSTANCER' for instances on them); transparent: mix
    with a transparent shader by the attribute's alpha (the splat opacity).
    """

    def build(nodes, links):
        attr = nodes.new("ShaderNodeAttribute")
        attr.attribute_type = attribute_type
        attr.attribute_name = attribute
        emission = nodes.new("ShaderNodeEmission")
        out = nodes.new("ShaderNodeOutputMaterial")
        links.new(attr.outputs["Color"], emission.inputs["Color"])
        chain = [attr, emission]
        shader = emission.outputs["Emission"]
        if transparent:
            clear = nodes.new("ShaderNodeBsdfTransparent")
            mix = nodes.new("ShaderNodeMixShader")
            links.new(attr.outputs["Alpha"], mix.inputs["Fac"])
            links.new(clear.outputs["BSDF"], mix.inputs[1])
            links.new(shader, mix.inputs[2])
            chain += [clear, mix]
            shader = mix.outputs["Shader"]
        links.new(shader, out.inputs["Surface"])
        for i, node in enumerate(chain + [out]):
            node.location = (220 * i - 440, 0)

    return node_material(name, build)


# ------------------------------------------------------------------ the node tree
class _Builder:
    def __init__(self, tree):
        self.nodes, self.links = tree.nodes, tree.links

    def node(self, kind: str, **settings):
        node = self.nodes.new(kind)
        for key, value in settings.items():
            setattr(node, key, value)
        return node

    def math(self, operation: str, a, b=None, c=None, clamp: bool = False):
        """A Math node's output; inputs are sockets or numbers."""
        node = self.node("ShaderNodeMath", operation=operation, use_clamp=clamp)
        for i, value in enumerate((a, b, c)):
            if value is None:
                continue
            if isinstance(value, (int, float)):
                node.inputs[i].default_value = value
            else:
                self.links.new(value, node.inputs[i])
        return node.outputs[0]

    def attribute(self, name: str, data_type: str):
        node = self.node("GeometryNodeInputNamedAttribute", data_type=data_type)
        node.inputs["Name"].default_value = name
        return node.outputs["Attribute"]

    def srgb_to_linear(self, value):
        """IEC 61966-2-1's inverse transfer function of a socket in [0, 1]."""
        low = self.math("DIVIDE", value, 12.92)
        high = self.math("POWER", self.math("MULTIPLY_ADD", value, 1 / 1.055, 0.055 / 1.055), 2.4)
        above = self.math("GREATER_THAN", value, 0.04045)
        return self.math("MULTIPLY_ADD", above, self.math("SUBTRACT", high, low), low)


def _build(tree) -> None:
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket(ELLIPSOIDS, in_out="INPUT", socket_type="NodeSocketBool")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    b = _Builder(tree)
    group_in, group_out = b.node("NodeGroupInput"), b.node("NodeGroupOutput")

    # splat_color: linear SH degree-0 colour, alpha = opacity
    split = b.node("FunctionNodeSeparateColor")
    b.links.new(b.attribute("radiance:base", "FLOAT_COLOR"), split.inputs[0])
    join = b.node("FunctionNodeCombineColor")
    for channel in ("Red", "Green", "Blue"):
        srgb = b.math("MULTIPLY_ADD", split.outputs[channel], C0, 0.5, clamp=True)
        b.links.new(b.srgb_to_linear(srgb), join.inputs[channel])
    b.links.new(split.outputs["Alpha"], join.inputs["Alpha"])
    store = b.node("GeometryNodeStoreNamedAttribute", data_type="FLOAT_COLOR", domain="POINT")
    store.inputs["Name"].default_value = "splat_color"
    b.links.new(group_in.outputs["Geometry"], store.inputs["Geometry"])
    b.links.new(join.outputs[0], store.inputs["Value"])

    # points: radius = twice the geometric-mean standard deviation
    scale = b.attribute("scale", "FLOAT_VECTOR")
    axes = b.node("ShaderNodeSeparateXYZ")
    b.links.new(scale, axes.inputs[0])
    volume = b.math("MULTIPLY", b.math("MULTIPLY", axes.outputs["X"], axes.outputs["Y"]), axes.outputs["Z"])
    radius = b.math("MULTIPLY", b.math("POWER", volume, 1 / 3), 2.0)
    set_radius = b.node("GeometryNodeSetPointRadius")
    b.links.new(store.outputs["Geometry"], set_radius.inputs["Points"])
    b.links.new(radius, set_radius.inputs["Radius"])
    points = b.node("GeometryNodeSetMaterial")
    points.inputs["Material"].default_value = attribute_material(POINT_MATERIAL)
    b.links.new(set_radius.outputs[0], points.inputs["Geometry"])

    # ellipsoids: a sphere per splat, rotated and scaled to ELLIPSOID_SIGMAS standard deviations
    sphere = b.node("GeometryNodeMeshIcoSphere")
    sphere.inputs["Radius"].default_value = 1.0
    sphere.inputs["Subdivisions"].default_value = 2
    sphere_material = b.node("GeometryNodeSetMaterial")
    sphere_material.inputs["Material"].default_value = attribute_material(ELLIPSOID_MATERIAL, "INSTANCER", transparent=False)
    b.links.new(sphere.outputs["Mesh"], sphere_material.inputs["Geometry"])
    sigmas = b.node("ShaderNodeVectorMath", operation="SCALE")
    sigmas.inputs["Scale"].default_value = ELLIPSOID_SIGMAS
    b.links.new(scale, sigmas.inputs[0])
    instance = b.node("GeometryNodeInstanceOnPoints")
    b.links.new(store.outputs["Geometry"], instance.inputs["Points"])
    b.links.new(sphere_material.outputs["Geometry"], instance.inputs["Instance"])
    b.links.new(b.attribute("rotation", "QUATERNION"), instance.inputs["Rotation"])
    b.links.new(sigmas.outputs["Vector"], instance.inputs["Scale"])

    switch = b.node("GeometryNodeSwitch", input_type="GEOMETRY")
    b.links.new(group_in.outputs[ELLIPSOIDS], switch.inputs["Switch"])
    b.links.new(points.outputs["Geometry"], switch.inputs["False"])
    b.links.new(instance.outputs["Instances"], switch.inputs["True"])
    b.links.new(switch.outputs[0], group_out.inputs["Geometry"])
    for i, node in enumerate(tree.nodes):
        node.location = (200 * (i % 8), -200 * (i // 8))


def node_tree():
    """The display node group (built, or rebuilt when a file holds an older version)."""
    tree = bpy.data.node_groups.get(TREE_NAME)
    if tree is not None and tree.get("mlx3d_display_version") == TREE_VERSION:
        return tree
    if tree is None:
        tree = bpy.data.node_groups.new(TREE_NAME, "GeometryNodeTree")
    else:
        tree.nodes.clear()
        tree.interface.clear()
    _build(tree)
    tree["mlx3d_display_version"] = TREE_VERSION
    return tree


# ------------------------------------------------------------------ objects
def is_display(modifier) -> bool:
    return modifier.type == "NODES" and modifier.name == MODIFIER_NAME


def _modifier(obj):
    modifier = obj.modifiers.get(MODIFIER_NAME)
    return modifier if modifier is not None and is_display(modifier) else None


def _ellipsoid_key(tree) -> str:
    return tree.interface.items_tree[ELLIPSOIDS].identifier


def _input(modifier, key: str):
    """A modifier input's value: ``properties.inputs`` from Blender 5.2, ID properties before."""
    if hasattr(modifier, "properties"):
        socket = getattr(modifier.properties.inputs, key, None)
        return None if socket is None else socket.value
    return modifier.get(key)


def _set_input(modifier, key: str, value) -> None:
    if hasattr(modifier, "properties"):
        getattr(modifier.properties.inputs, key).value = value
    else:
        modifier[key] = value


def has_ellipsoids(obj) -> bool:
    modifier = _modifier(obj)
    return bool(modifier is not None and modifier.node_group is not None and _input(modifier, _ellipsoid_key(modifier.node_group)))


def ensure(obj, own_display: bool, ellipsoids: bool | None = None) -> bool:
    """Give ``obj`` the display it needs: the modifier where Blender cannot draw splats
    (``own_display``) or while ellipsoids are shown; ``ellipsoids`` None keeps the current
    choice. True if anything changed."""
    show = has_ellipsoids(obj) if ellipsoids is None else ellipsoids
    modifier = _modifier(obj)
    if not (own_display or show):
        if modifier is None:
            return False
        obj.modifiers.remove(modifier)
        return True
    changed = False
    tree = node_tree()
    if modifier is None:
        modifier = obj.modifiers.new(MODIFIER_NAME, "NODES")
        changed = True
    if modifier.node_group is not tree:
        modifier.node_group = tree
        changed = True
    key = _ellipsoid_key(tree)
    if bool(_input(modifier, key)) != show:
        _set_input(modifier, key, show)
        obj.update_tag()
        changed = True
    return changed


def set_ellipsoids(obj, show: bool) -> None:
    """Show each splat as an ellipsoid, or go back to the default display."""
    ensure(obj, current().own_display, ellipsoids=show)


def remove_legacy(obj) -> bool:
    """Remove the earlier add-on's ellipsoid modifier; True if the object had it."""
    modifier = obj.modifiers.get(LEGACY_MODIFIER)
    if modifier is None:
        return False
    obj.modifiers.remove(modifier)
    return True
