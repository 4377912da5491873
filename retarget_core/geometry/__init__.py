"""Geometry shared by the refinement stages and the networks: posing point subsets (:mod:`point_poser`),
sentinel points and (point, segment) triples in the part SDFs (:mod:`triples`), the pairs the judge tests
(:mod:`judged_pairs`), closest points on triangles (:mod:`closest_point`) and a triangle tree refit per posed
frame (:mod:`triangle_bvh`). Below both ``refine`` and ``model``: imports run ``pipeline -> refine -> model -> geometry``."""
