"""Optional "ellipsoids" display: a geometry-nodes modifier that instances a
sphere on every splat, rotated by the unit quaternion ``rotation`` (derived
from ``rot``) and scaled to ``ELLIPSOID_SIGMAS``
standard deviations (``exp(log_scale)``), coloured by ``splat_color``.

Display only: the modifier never changes the splat attributes that export
reads, and removing it restores the plain point display.
"""

from __future__ import annotations

import bpy

from .splat_object import attribute_material

MODIFIER_NAME = "MLX3D Ellipsoids"
TREE_NAME = "MLX3D Splat Ellipsoids"
MATERIAL_NAME = "MLX3D Splat Ellipsoid"
ELLIPSOID_SIGMAS = 2.0


def _node_tree():
    tree = bpy.data.node_groups.get(TREE_NAME)
    if tree is not None:
        return tree
    tree = bpy.data.node_groups.new(TREE_NAME, "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = tree.nodes, tree.links
    group_in = nodes.new("NodeGroupInput")
    group_out = nodes.new("NodeGroupOutput")
    sphere = nodes.new("GeometryNodeMeshIcoSphere")
    sphere.inputs["Radius"].default_value = 1.0
    sphere.inputs["Subdivisions"].default_value = 2
    set_material = nodes.new("GeometryNodeSetMaterial")
    set_material.inputs["Material"].default_value = attribute_material(MATERIAL_NAME, "INSTANCER", transparent=False)
    rotation = nodes.new("GeometryNodeInputNamedAttribute")
    rotation.data_type = "QUATERNION"
    rotation.inputs["Name"].default_value = "rotation"
    log_scale = nodes.new("GeometryNodeInputNamedAttribute")
    log_scale.data_type = "FLOAT_VECTOR"
    log_scale.inputs["Name"].default_value = "log_scale"
    split = nodes.new("ShaderNodeSeparateXYZ")
    join = nodes.new("ShaderNodeCombineXYZ")
    links.new(log_scale.outputs["Attribute"], split.inputs["Vector"])
    for axis in "XYZ":
        exp = nodes.new("ShaderNodeMath")
        exp.operation = "EXPONENT"
        links.new(split.outputs[axis], exp.inputs[0])
        links.new(exp.outputs["Value"], join.inputs[axis])
    sigmas = nodes.new("ShaderNodeVectorMath")
    sigmas.operation = "SCALE"
    sigmas.inputs["Scale"].default_value = ELLIPSOID_SIGMAS
    links.new(join.outputs["Vector"], sigmas.inputs["Vector"])
    instance = nodes.new("GeometryNodeInstanceOnPoints")
    links.new(group_in.outputs["Geometry"], instance.inputs["Points"])
    links.new(sphere.outputs["Mesh"], set_material.inputs["Geometry"])
    links.new(set_material.outputs["Geometry"], instance.inputs["Instance"])
    links.new(rotation.outputs["Attribute"], instance.inputs["Rotation"])
    links.new(sigmas.outputs["Vector"], instance.inputs["Scale"])
    links.new(instance.outputs["Instances"], group_out.inputs["Geometry"])
    return tree


def has_ellipsoids(obj) -> bool:
    return obj.modifiers.get(MODIFIER_NAME) is not None


def set_ellipsoids(obj, show: bool) -> None:
    """Add or remove the ellipsoid display modifier on a splat object."""
    modifier = obj.modifiers.get(MODIFIER_NAME)
    if show and modifier is None:
        modifier = obj.modifiers.new(MODIFIER_NAME, "NODES")
        modifier.node_group = _node_tree()
    elif not show and modifier is not None:
        obj.modifiers.remove(modifier)
