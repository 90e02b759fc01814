"""Geometry for Geodesic Control: tube geodesics, winding and linking, knot
invariants, and geodesics on object meshes.

Modules (imported on demand, so that this package stays light):
``tube`` (bounding tube and winding target line, paper §4.2), ``winding``
(Eq. 1, Gauss linking integral, writhe), ``knots`` (closing ropes far away and
identifying their knots), ``knot_invariants`` (Gauss/PD codes, Alexander,
signature, Jones), ``mesh_geodesic`` and ``mesh_prep`` (target lines on
objects, §5.1).
"""
