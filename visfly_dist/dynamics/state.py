"""``QuadState``: the batched, immutable state of N quadrotors."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch


@dataclass(frozen=True)
class QuadState:
    """State of N quadrotors; every field is a tensor with the batch first.

    Attributes:
        pos: (N, 3) m, world frame (z up).
        vel: (N, 3) m/s, world frame.
        quat: (N, 4) unit quaternion ``wxyz``, body (FLU) to world.
        omega: (N, 3) rad/s, body rates in the body frame.
        rotor: (N, 4) rad/s, rotor speeds (rotor order of ``Airframe``).
        ground_contact: (N,) bool, the agent was at or below the ground plane ``z = 0`` at the end of
            some physics substep of the last control step (a resting or crashed drone). Reported,
            never hidden: the simple ground reaction (see ``Quadrotor``) only stops it sinking.
        action_queue: (N, D, 4) actions in [-1, 1] waiting to be applied, oldest first; ``D`` is the
            action delay in control steps (0 without delay).
    """

    pos: torch.Tensor
    vel: torch.Tensor
    quat: torch.Tensor
    omega: torch.Tensor
    rotor: torch.Tensor
    ground_contact: torch.Tensor
    action_queue: torch.Tensor

    @property
    def num_agents(self) -> int:
        return self.pos.shape[0]

    def pose(self) -> torch.Tensor:
        """(N, 7) rows ``[x, y, z, qw, qx, qy, qz]``, the wire's pose layout."""
        return torch.cat((self.pos, self.quat), dim=1)

    def detach(self) -> QuadState:
        """The same state cut from the autograd graph (truncated BPTT)."""
        return QuadState(**{f.name: getattr(self, f.name).detach() for f in fields(self)})

    def put_rows(self, index: torch.Tensor, rows: QuadState) -> QuadState:
        """This state with agents ``index`` (``(k,)`` long) taken from ``rows`` (a state of ``k``
        agents, in that order): what :meth:`where` gives, made from the ``k`` new rows only."""
        return QuadState(**{f.name: getattr(self, f.name).index_copy(0, index, getattr(rows, f.name))
                            for f in fields(self)})

    @staticmethod
    def where(mask: torch.Tensor, a: QuadState, b: QuadState) -> QuadState:
        """Agent-wise select: ``a``'s agent ``i`` where ``mask[i]``, else ``b``'s (masked resets).

        Args:
            mask: (N,) bool.
            a: state taken where ``mask`` is true.
            b: state taken where ``mask`` is false.
        """
        out = {}
        for f in fields(QuadState):
            x, y = getattr(a, f.name), getattr(b, f.name)
            m = mask.reshape(mask.shape + (1,) * (x.dim() - 1))
            out[f.name] = torch.where(m, x, y)
        return QuadState(**out)
