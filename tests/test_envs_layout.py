"""Observation layouts: the sizes in docs/envs.md (formulas in N, present or not per ablation) are
the environment's, for every history length of the paper's ablation and every Section IV-C ablation;
the observations the environment returns have those sizes and carry the named quantities."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from envs_support import ROBOT, exact_config, make_env, recorded_reference

from opt2skill.envs import ABLATIONS, layout, tracking_config

DOC = Path(__file__).resolve().parents[1] / "docs" / "envs.md"


def documented(group: str) -> list[tuple[str, str, str]]:
    """(term, size formula, N = 10 slice) rows of the documented table of `group`."""
    text = DOC.read_text()
    block = text.split(f"<!-- layout:{group} -->")[1].split("<!-- /layout -->")[0]
    rows = []
    for line in block.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 3 and cells[0].startswith("`"):
            rows.append((cells[0].strip("`"), cells[1], cells[2]))
    assert rows, f"no {group} layout table in {DOC}"
    return rows


def size_of(formula: str, n: int, force: bool, torque: bool, contacts: int = 2) -> int:
    """'20 N' -> 20 n; '3 C' -> 3 contacts; '20 (T)' -> 20 with the reference torque, else 0; '(F)' likewise."""
    needs = re.findall(r"\((F|T)\)", formula)
    if ("F" in needs and not force) or ("T" in needs and not torque):
        return 0
    expr = re.sub(r"\((F|T)\)", "", formula).replace("N", f"*{n}").replace("C", f"*{contacts}")
    return int(eval(expr, {}))


@pytest.mark.parametrize("ablation", list(ABLATIONS))
@pytest.mark.parametrize("history", [0, 5, 10, 15])
@pytest.mark.parametrize("contacts", [2, 4])
def test_layout_sizes_match_the_documentation(history, ablation, contacts):
    config = tracking_config("squat", ablation, history)
    force, torque = ABLATIONS[ablation]
    lay = layout(config.observations, ROBOT.nu, contacts)
    for group in ("actor", "critic"):
        expected = [(t, size_of(f, history, force, torque, contacts)) for t, f, _ in documented(group)]
        expected = [(t, s) for t, s in expected if s]
        got = [(name, size) for name, _, _, size in lay.rows(group)]
        assert got == expected, group
        slices = getattr(lay, group)
        assert list(slices.values())[0].start == 0
        assert all(a.stop == b.start for a, b in zip(list(slices.values()), list(slices.values())[1:]))


def test_documented_slices_are_those_of_n10_and_the_totals_are_stated():
    lay = layout(tracking_config("squat").observations, ROBOT.nu, len(ROBOT.config.feet))
    for group in ("actor", "critic"):
        slices = getattr(lay, group)
        for term, _, where in documented(group):
            lo, hi = (int(x) for x in where.split(":"))
            assert (slices[term].start, slices[term].stop) == (lo, hi), term
    text = DOC.read_text()
    assert f"actor: {lay.actor_dim}" in text and f"critic: {lay.critic_dim}" in text
    assert (lay.actor_dim, lay.critic_dim) == (481, 605)
    hands = layout(tracking_config("squat").observations, ROBOT.nu, 4)  # feet and hands
    assert f"{hands.actor_dim} and {hands.critic_dim}" in text and (hands.actor_dim, hands.critic_dim) == (487, 617)


def test_observation_vectors_carry_the_named_quantities():
    traj, targets = recorded_reference(steps=20)
    env = make_env([traj], exact_config())
    env.reset_worlds(np.array([0]), np.array([0]), np.array([0]))
    for t in targets[:5]:
        result = env.step(env.actions_for_targets(t[None]))
    actor, critic = result.actor[0], result.critic[0]
    assert actor.shape == (env.actor_dim,) and critic.shape == (env.critic_dim,) and actor.dtype == np.float32
    sa, sc, m = env.layout.actor, env.layout.critic, env.m

    def a(name):
        return actor[sa[name]]

    def c(name):
        return critic[sc[name]]

    np.testing.assert_allclose(c("base_quat"), m.base_quat[0], atol=1e-6)
    np.testing.assert_allclose(c("projected_gravity"), m.gravity[0], atol=1e-6)
    np.testing.assert_allclose(c("kp"), ROBOT.config.kp, rtol=1e-6)  # nominal gains: randomization off
    np.testing.assert_allclose(c("ref_joint_pos"), traj.qpos[6, 7:], atol=1e-6)  # frame t + 1 (t = 5)
    np.testing.assert_allclose(c("ref_joint_torque"), traj.joint_torque[5], rtol=1e-5, atol=1e-4)  # frame t
    np.testing.assert_allclose(a("ref_base_lin_vel"), traj.base_lin_vel[6], atol=1e-6)
    np.testing.assert_allclose(c("ref_ee_pos"), traj.ee_pos_base[6, :4].ravel(), atol=1e-6)  # hands, feet
    weight = ROBOT.mj_model.body_mass.sum() * 9.81
    assert abs(c("contact_force")[[2, 5]].sum() - weight) < 0.1 * weight  # standing: the feet carry it
    np.testing.assert_array_equal(a("joint_vel"), c("joint_vel"))  # no noise in this config
    env.close()
