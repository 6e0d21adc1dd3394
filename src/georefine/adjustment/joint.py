"""Several built problems adjusted as one: a joint problem tied by the blocks they share (docs/ARCHITECTURE.md §4.4).

Each problem keeps its own observation models and block names; :func:`merge_problems` puts them
into one :class:`~georefine.adjustment.problem.Problem` in which every block of problem ``k`` is
renamed ``prefix_k + name``, except the names declared *shared* (e.g. the planar objects seen by
several flights, one boresight, one LiDAR time offset: the caller names them, this layer knows no
workflow). A shared block takes its start values, manifold and constant mask from the first
problem that has it; the others must agree in shape and manifold.

Every observation group is wrapped in a :class:`PrefixedGroup`, which implements the
:class:`~georefine.adjustment.blocks.ObservationGroup` protocol: its ``linearize`` hands the
wrapped group a mapping view in which the group's own block names resolve to the prefixed ones
(shared names unchanged) and renames the ``block`` of every returned
:class:`~georefine.adjustment.blocks.JacobianBlock` back to the joint names. Group names are
prefixed too; a group declared shared (a prior on a shared block only, present in every problem)
is included once, unprefixed, from the first problem that has it.

The joint problem is solved by the existing solver (the column layout, the sparse factorisation
and the selected inverse see one problem). :meth:`JointProblem.part` gives problem ``k``'s view
of it (:class:`PartView`): the read interface of a ``Problem`` (values, blocks, covariances,
variance components) under the part's own names, so the read-out functions written for one
problem (the spline, the IMU errors, the posterior sigma) work on each part unchanged;
:meth:`JointProblem.write_back` copies the solution into the original problems.
"""

from __future__ import annotations

from collections.abc import Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from georefine.adjustment.blocks import JacobianBlock, Linearization, ObservationGroup, ParameterBlock
from georefine.adjustment.problem import Problem
from georefine.adjustment.robust import RobustLoss
from georefine.adjustment.solver import SolveResult

__all__ = ["JointProblem", "PartView", "PrefixedGroup", "PrefixedValues", "merge_problems"]


class PrefixedValues(Mapping):
    """A read-only view of the joint values under one part's block names.

    ``view[name]`` is ``values[prefix + name]``, or ``values[name]`` for a shared name. It
    iterates over the part's names present in ``values`` (shared ones included).
    """

    def __init__(self, values: Mapping[str, np.ndarray], prefix: str, shared: Collection[str]) -> None:
        self._values, self._prefix, self._shared = values, prefix, frozenset(shared)

    def joint_name(self, name: str) -> str:
        return name if name in self._shared else self._prefix + name

    def __getitem__(self, name: str) -> np.ndarray:
        return self._values[self.joint_name(name)]

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and self.joint_name(name) in self._values

    def __iter__(self) -> Iterator[str]:
        p = self._prefix
        for name in self._values:
            if name in self._shared:
                yield name
            elif name.startswith(p):
                yield name[len(p):]

    def __len__(self) -> int:
        return sum(1 for _ in self)


@dataclass
class PrefixedGroup:
    """An observation group of one part, seen from the joint problem (module docstring).

    ``name`` is the joint name (``prefix + group.name``, or the group's own for a shared one);
    the robust loss and the consumed redundancy are the wrapped group's.
    """

    group: ObservationGroup
    prefix: str
    shared: frozenset[str] = field(default_factory=frozenset)
    name: str = ""

    def __post_init__(self) -> None:
        self.shared = frozenset(self.shared)
        if not self.name:
            self.name = self.prefix + self.group.name

    @property
    def loss(self) -> RobustLoss | None:
        return self.group.loss

    @property
    def consumed_redundancy(self) -> float:
        return float(self.group.consumed_redundancy)

    def joint_name(self, name: str) -> str:
        return name if name in self.shared else self.prefix + name

    def linearize(self, values: Mapping[str, np.ndarray], jacobians: bool = True) -> Linearization:
        """The wrapped group's linearisation at the joint ``values``, its Jacobian blocks under the joint names."""
        lin = self.group.linearize(PrefixedValues(values, self.prefix, self.shared), jacobians)
        if not lin.jacobians:
            return lin
        renamed = [JacobianBlock(self.joint_name(j.block), j.rows, j.elements, j.values) for j in lin.jacobians]
        return Linearization(lin.residuals, renamed, lin.observation)


@dataclass
class JointProblem:
    """The merged problem (:func:`merge_problems`), its parts and how their names map into it."""

    problem: Problem
    parts: tuple[Problem, ...]
    prefixes: tuple[str, ...]
    shared: frozenset[str]
    shared_groups: frozenset[str]

    def joint_name(self, k: int, name: str) -> str:
        """The joint name of block ``name`` of part ``k``."""
        return name if name in self.shared else self.prefixes[k] + name

    def part(self, k: int) -> PartView:
        """Part ``k``'s view of the joint problem (its own block and group names)."""
        return PartView(self, k)

    def write_back(self) -> None:
        """Copy the joint problem's current values into every part's own problem."""
        for k, part in enumerate(self.parts):
            for name in part.blocks:
                part.set_values(name, self.problem.values(self.joint_name(k, name)))

    def part_groups(self, k: int) -> tuple[str, ...]:
        """The joint names of the groups that came from part ``k`` (shared ones included where it has them)."""
        out = []
        for g in self.parts[k].groups:
            out.append(g.name if g.name in self.shared_groups else self.prefixes[k] + g.name)
        return tuple(out)

    def part_solve(self, k: int, solve: SolveResult) -> SolveResult:
        """``solve`` (the joint problem's) with only part ``k``'s group statistics, under the part's own names.

        The overall figures (cost, redundancy, variance factor, iterations) stay the joint problem's.
        """
        p = self.prefixes[k]
        own = set(self.part_groups(k))
        groups = tuple(replace(g, name=g.name if g.name in self.shared_groups else g.name[len(p):])
                       for g in solve.groups if g.name in own)
        return replace(solve, groups=groups)


class PartView:
    """One part of a :class:`JointProblem` seen through the read interface of a
    :class:`~georefine.adjustment.problem.Problem` (values, blocks, constant masks, covariances,
    variance components), under the part's own block and group names.

    :meth:`expect_covariance` is left to the joint problem (:meth:`JointProblem.problem`): the
    parts' queries share one posterior, so the caller states their total once; here it does nothing.
    Variance-component pools name groups by the part's names; each name stands for that group
    in every part (a pool of ``planes`` is the planes of all parts), so every part asks for the
    same components, which the joint problem estimates once.
    """

    def __init__(self, joint: JointProblem, k: int) -> None:
        self._joint, self._k = joint, k

    @property
    def joint(self) -> JointProblem:
        return self._joint

    def _name(self, name: str) -> str:
        return self._joint.joint_name(self._k, name)

    def values(self, name: str) -> np.ndarray:
        return self._joint.problem.values(self._name(name))

    def constant(self, name: str) -> np.ndarray:
        return self._joint.problem.constant(self._name(name))

    def set_values(self, name: str, values: np.ndarray) -> None:
        self._joint.problem.set_values(self._name(name), values)

    @property
    def blocks(self) -> Mapping[str, ParameterBlock]:
        jb = self._joint.problem.blocks
        return {name: jb[self._name(name)] for name in self._joint.parts[self._k].blocks}

    @property
    def groups(self) -> tuple[ObservationGroup, ...]:
        return self._joint.parts[self._k].groups

    def covariance(self, block: str, elements: np.ndarray | None = None, scale_by_variance_factor: bool = True,
                   diagonal: bool = False) -> np.ndarray:
        return self._joint.problem.covariance(self._name(block), elements, scale_by_variance_factor, diagonal)

    def expect_covariance(self, columns: int) -> None:
        """Nothing: the joint problem is told the parts' total (class docstring)."""

    def posterior_seconds(self) -> dict[str, float]:
        return self._joint.problem.posterior_seconds()

    def use_variance_components(self, pools: Sequence[Sequence[str]] | None = None, **kwargs):
        joint = self._joint
        if pools is not None:
            pools = [[name for k in range(len(joint.parts)) for name in joint.part_groups(k)
                      if _own_name(joint, k, name) in set(pool)] for pool in pools]
            pools = [sorted(set(p)) for p in pools]
        return joint.problem.use_variance_components(pools, **kwargs)


def _own_name(joint: JointProblem, k: int, name: str) -> str:
    """The part's own name of joint group ``name`` of part ``k``."""
    return name if name in joint.shared_groups else name[len(joint.prefixes[k]):]


def merge_problems(problems: Sequence[Problem], prefixes: Sequence[str], shared: Collection[str] = (),
                   shared_groups: Collection[str] = ()) -> JointProblem:
    """One problem of all ``problems`` (module docstring).

    Parameters
    ----------
    problems
        Built problems (not modified; their current values start the joint problem).
    prefixes
        One distinct prefix per problem, e.g. ``"f1/"``.
    shared
        Block names that are one block in the joint problem wherever a part has them.
    shared_groups
        Group names included once, unprefixed (from the first part that has them): groups that
        read only shared blocks, such as a prior on a shared calibration.

    Raises
    ------
    ValueError
        Prefixes not distinct or not as many as the problems; a shared block whose shape or
        manifold differs between parts; a shared group that reads a block that is not shared.
    """
    problems, prefixes = tuple(problems), tuple(prefixes)
    if len(problems) != len(prefixes) or len(set(prefixes)) != len(prefixes):
        raise ValueError(f"merge_problems: need one distinct prefix per problem, found {prefixes!r} "
                         f"for {len(problems)} problems")
    shared, shared_groups = frozenset(shared), frozenset(shared_groups)
    joint = Problem()
    first_shared: dict[str, ParameterBlock] = {}
    for k, (part, prefix) in enumerate(zip(problems, prefixes)):
        for name, block in part.blocks.items():
            if name in shared:
                seen = first_shared.get(name)
                if seen is None:
                    first_shared[name] = block
                elif seen.manifold != block.manifold or seen.values.shape != block.values.shape:
                    raise ValueError(f"merge_problems: shared block {name!r} differs between parts "
                                     f"({seen.manifold} {seen.values.shape} against {block.manifold} "
                                     f"{block.values.shape} in part {k})")
                continue
            joint.add_block(prefix + name, block.values, block.manifold, block.constant)
    for name, block in first_shared.items():  # the shared blocks after every part's own
        joint.add_block(name, block.values, block.manifold, block.constant)
    added: set[str] = set()
    for part, prefix in zip(problems, prefixes):
        for group in part.groups:
            if group.name in shared_groups:
                if group.name in added:
                    continue
                added.add(group.name)
                joint.add_group(PrefixedGroup(group, prefix, shared, name=group.name))
            else:
                joint.add_group(PrefixedGroup(group, prefix, shared))
    result = JointProblem(joint, problems, prefixes, shared, shared_groups)
    for name in added:  # a shared group must not read a part's own block
        group = next(g for g in joint.groups if g.name == name)
        lin = group.linearize({n: b.values for n, b in joint.blocks.items()}, True)
        own = sorted({j.block for j in lin.jacobians if j.block not in shared})
        if own:
            raise ValueError(f"merge_problems: shared group {name!r} reads blocks that are not shared: {own}")
    return result
