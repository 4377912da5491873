"""Small built cases for the collision stage's posed-mesh term and contact gap (no real bodies: fast)."""

from __future__ import annotations

import torch

from retarget_core.refine.collision_mesh import MeshPairs, MeshTerms, mesh_energy, mesh_signed_distance


def _one_triangle(x: torch.Tensor, sign: float) -> tuple[MeshTerms, torch.Tensor]:
    tri = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # normal +z
    posed = torch.cat([x[None], tri])[None]  # (1, 4, 3): the point, then the triangle
    terms = MeshTerms(torch.tensor([0]), torch.tensor([0]), torch.tensor([[1, 2, 3]]), torch.tensor([sign]))
    return terms, posed


def test_mesh_signed_distance_is_the_plane_distance_with_the_pair_sign() -> None:
    terms, posed = _one_triangle(torch.tensor([0.2, 0.2, -0.03]), -1.0)  # below, and "outside" is -z here
    assert torch.allclose(mesh_signed_distance(terms, posed), torch.tensor([0.03]))
    terms, posed = _one_triangle(torch.tensor([0.2, 0.2, -0.03]), 1.0)  # outside is +z: 3 cm inside
    assert torch.allclose(mesh_signed_distance(terms, posed), torch.tensor([-0.03]))


def test_mesh_energy_pushes_an_inside_point_out_and_leaves_an_outside_one() -> None:
    x = torch.tensor([0.2, 0.2, -0.02], requires_grad=True)
    terms, posed = _one_triangle(x, 1.0)
    e = mesh_energy(terms, posed, scale=1.0, clearance=0.001)
    assert abs(float(e) - 2.1**2) < 1e-4  # 2 cm deep + 1 mm clearance, in cm^2
    e.backward()
    assert x.grad is not None and float(x.grad[2]) < 0  # descent moves the point up, out of the part
    terms, posed = _one_triangle(torch.tensor([0.2, 0.2, 0.02]), 1.0)
    assert float(mesh_energy(terms, posed, scale=1.0, clearance=0.001)) == 0.0


def test_mesh_pairs_union_keeps_one_pair_per_frame_and_vertex_preferring_the_newer() -> None:
    def pairs(frames: list[int], verts: list[int], depth: float) -> MeshPairs:
        n = len(frames)
        return MeshPairs(torch.tensor(frames), torch.tensor(verts), torch.zeros(n, 3, dtype=torch.long),
                         torch.ones(n), torch.full((n,), depth))  # fmt: skip

    old, new = pairs([0, 0, 1], [5, 6, 5], 0.01), pairs([0, 2], [5, 7], 0.02)
    u = old.union(new, num_vertices=10)
    got = {(int(f), int(v)): round(float(d), 6) for f, v, d in zip(u.frame, u.vertex, u.depth, strict=True)}
    assert got == {(0, 5): 0.02, (0, 6): 0.01, (1, 5): 0.01, (2, 7): 0.02}
    assert torch.allclose(u.max_depth(3), torch.tensor([0.02, 0.01, 0.02]))


def test_the_mesh_test_poses_only_what_it_reads_and_reads_the_same() -> None:
    """The posed-torso test skins only the vertices it reads (testers, dragged skin, the torso part): their rows
    are bit-identical to the whole body's, and the pairs found on a pose equal those on the fully posed body."""
    from pathlib import Path

    import numpy as np

    from retarget_core import kinematics
    from retarget_core.loading import load_character
    from retarget_core.refine.collision_mesh import find_mesh_pairs, mesh_pairs_of_motion, mesh_setup

    loaded = load_character(Path(__file__).parents[2] / "retarget_core/data/samples/characters/mh_male_bulky.glb")
    ch = loaded.character
    setup = mesh_setup(ch, loaded.mapping)
    read = setup.read_vertices()
    assert 0 < len(read) < ch.num_vertices and np.all(np.diff(read) > 0)
    rot = ch.skeleton.rest_rotations.float().repeat(3, 1, 1)
    arms = [loaded.mapping.joints[n] for n in ("LeftArm", "RightArm")]
    rot[:, arms] = torch.tensor([0.0, 0.0, 0.6, 0.8])  # the arms turned into the torso's sides
    trans = ch.skeleton.rest_translations.float().repeat(3, 1, 1)
    grot, gpos = kinematics.forward_kinematics(ch.skeleton.parents, rot, trans)
    full = ch.pose_vertices(grot, gpos)
    assert torch.equal(ch.pose_rows(torch.from_numpy(read), grot, gpos), full[:, torch.from_numpy(read)])
    near = 0.01
    want = find_mesh_pairs(setup, full.double().numpy(), near, 0.05 * ch.height / 1.80)
    got = mesh_pairs_of_motion(ch, setup, rot, trans, torch.arange(3), near)
    assert want.count > 0
    for k in ("frame", "vertex", "tri", "sign", "depth"):
        assert torch.equal(getattr(got, k), getattr(want, k)), k


def test_the_mesh_test_finds_what_libigl_finds_on_a_posed_body() -> None:
    """On the bulky sample with the arms turned into its sides, the pairs are libigl's (closest triangle and fast
    winding number per frame): every pair's depth is libigl's distance, signed by its winding number, and every
    tester vertex libigl sees inside (or within ``near``) through a triangle that is not a cap is a pair."""
    from pathlib import Path

    import igl
    import numpy as np

    from retarget_core import kinematics
    from retarget_core.loading import load_character
    from retarget_core.refine.collision_mesh import _queries, find_mesh_pairs, mesh_setup

    loaded = load_character(Path(__file__).parents[2] / "retarget_core/data/samples/characters/mh_male_bulky.glb")
    ch = loaded.character
    setup = mesh_setup(ch, loaded.mapping)
    rot = ch.skeleton.rest_rotations.float().repeat(4, 1, 1)
    arms = [loaded.mapping.joints[n] for n in ("LeftArm", "RightArm")]
    for k, angle in enumerate((1.1, 1.2, 1.29, 1.4)):  # the arms turned into the torso's sides, more and more
        rot[k, arms] = torch.tensor([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)]).float()
    trans = ch.skeleton.rest_translations.float().repeat(4, 1, 1)
    posed = ch.pose_vertices(*kinematics.forward_kinematics(ch.skeleton.parents, rot, trans)).double().numpy()
    near, reach = 0.01, 0.05 * ch.height / 1.80
    got = find_mesh_pairs(setup, posed, near, reach)
    part = setup.body.part("torso")
    assert part is not None and got.count > 0 and bool((got.depth > 0).any())
    found = {(int(f), int(v)): float(d) for f, v, d in zip(got.frame, got.vertex, got.depth, strict=True)}
    frame, vertex = _queries(setup, "torso", posed, reach)
    for f in range(len(posed)):
        local = part.posed(posed[f])
        q_idx = vertex[frame == f].numpy()
        d2, face, _ = igl.point_mesh_squared_distance(posed[f][q_idx], local, part.faces)
        d = np.sqrt(d2)
        inside = np.abs(igl.fast_winding_number(local, part.faces, posed[f][q_idx])) > 0.5
        for v, dist, ins, cap in zip(q_idx, d, inside, part.is_cap[face], strict=True):
            if (f, int(v)) in found:
                assert abs(found[(f, int(v))] - (dist if ins else -dist)) < 1e-6
            elif dist < reach:
                assert cap or not (ins or dist < near), (f, v)


def test_the_mesh_test_finds_a_chin_bowed_into_the_chest() -> None:
    """The head's vertices are tested against the posed torso too (the judge's head %v): with the neck and head
    bowed until the judge counts the chin inside the chest, head vertices are among the pairs, inside."""
    from pathlib import Path

    import numpy as np
    import roma

    from retarget_core import rotations as rot
    from retarget_core.loading import load_character
    from retarget_core.metrics.acceptance import measure_acceptance
    from retarget_core.metrics.acceptance_body import PARTS
    from retarget_core.motion import Motion
    from retarget_core.refine.collision_mesh import mesh_pairs_of_motion, mesh_setup

    loaded = load_character(Path(__file__).parents[2] / "retarget_core/data/samples/characters/mh_male_bulky.glb")
    ch, mapping = loaded.character, loaded.mapping
    setup = mesh_setup(ch, mapping)
    head = np.nonzero(setup.body.part_of_vertex == PARTS.index("head"))[0]
    assert len(setup.testers["head"]) and np.isin(setup.testers["head"], head).all()
    sk = ch.skeleton
    g_rest, _ = sk.rest_global()
    r = sk.rest_rotations.repeat(2, 1, 1)
    for j in (mapping.joints["Neck"], mapping.joints["Head"]):  # each bows 0.5 rad forward about the world x axis
        bow = roma.rotvec_to_unitquat(torch.tensor([0.5, 0.0, 0.0], dtype=g_rest.dtype))
        r[1, j] = rot.mul(sk.rest_rotations[j], rot.mul(roma.quat_conjugation(g_rest[j]), rot.mul(bow, g_rest[j])))
    t = sk.rest_translations.repeat(2, 1, 1)
    judged = measure_acceptance(ch, mapping, Motion(sk, 30.0, r, t, "bow"))
    assert judged.head_count[0] == 0 and judged.head_count[1] > 0  # the built case: upright, then the chin in
    pairs = mesh_pairs_of_motion(ch, setup, r, t, torch.arange(2), 0.01)
    chin = pairs.select(torch.from_numpy(np.isin(pairs.vertex.numpy(), head)) & (pairs.depth > 0))
    assert chin.count > 0 and set(chin.frame.tolist()) == {1}
