"""What the tests share: readings stratified where failures hide (near gratings, near the base, at the tip,
gratings missing), and a child process that Ctrl-C reaches."""

from __future__ import annotations

import signal

import torch

import torchrod as tr

F64 = torch.float64


def stratified_readings(rod: tr.Rod, gen: torch.Generator, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """n noisy readings (noise 0.1 1/m) of 1-3 forces: a force near a grating, near the base, at the tip or anywhere,
    in turn; every third reading with two gratings missing."""
    q = torch.tensor(rod.gratings, dtype=F64)
    s, f, h = [], [], []
    for i in range(n):
        k = 1 + i % 3
        where = 0.02 + 0.27 * torch.rand(k, dtype=F64, generator=gen)
        kind = i % 4
        if kind == 0:
            near = q[int(torch.randint(0, len(q), (1,), generator=gen))]
            where[0] = near + 4e-4 * (torch.rand(1, dtype=F64, generator=gen) - 0.5)
        elif kind == 1:
            where[0] = 0.004 + 0.01 * torch.rand(1, dtype=F64, generator=gen)
        elif kind == 2:
            where[0] = rod.length - 1e-3
        s.append(torch.cat([where, torch.zeros(3 - k, dtype=F64)]))
        f.append(torch.cat([0.9 * torch.randn(k, 2, dtype=F64, generator=gen), torch.zeros(3 - k, 2, dtype=F64)]))
        h.append(k)
    active = torch.arange(3)[None, :] < torch.tensor(h)[:, None]
    u = tr.simulate(rod, tr.PointForces(torch.stack(s), torch.stack(f), active)).grating_curvature
    u = u + 0.1 * torch.randn(u.shape, dtype=F64, generator=gen)
    mask = torch.ones(n, rod.num_gratings, dtype=torch.bool)
    mask[::3, 3] = False
    mask[::3, 9] = False
    return u, mask


def interruptible() -> None:
    """``preexec_fn`` of a child process that a test interrupts with SIGINT: Ctrl-C reaches it as it reaches a
    terminal's foreground job. A process started with SIGINT ignored (as background jobs are, or as any library of
    the parent may have left it) keeps ignoring it, and Python installs no KeyboardInterrupt handler then."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
