"""Rollout stage, placing tokens: a token's 10 Hz poses from its start pose, the pose before it and
its poses in its own start frame (the vocabulary's six contour poses, start included).

``interpolation="spline"`` (the default of rollouts): the token's end pose is placed and the four
frames in between follow a cubic Hermite curve (:func:`hermite_frames`) whose tangents are the
previous token's displacement and this one's, so that speed and yaw rate run on smoothly across
token boundaries. ``"contour"``: the token's own contour poses. The engine places the tokens it
draws this way, and collision-aware sampling checks candidate tokens along the same frames.
"""

from __future__ import annotations

import torch

from ..scenario import wrap_angle

INTERPOLATIONS = ("spline", "contour")
MAX_LEAD = 2.8  # the start tangent of a token's curve is capped at this many times its displacement
_HERMITE_S = torch.tensor([0.2, 0.4, 0.6, 0.8], dtype=torch.float64)  # the in-between frames of a token, as a fraction of it


def token_frames(local: torch.Tensor, start: torch.Tensor, before: torch.Tensor, interpolation: str = "spline") -> torch.Tensor:
    """[..., 5, 3] the 10 Hz poses (x, y, heading) after ``start`` [..., 3] of tokens whose poses in
    their start frame are ``local`` [..., 6, 3]; ``before`` [..., 3] is where the previous token
    started (NaN: none), read by the spline only."""
    if interpolation == "contour":
        return compose_torch(start[..., None, :], local[..., 1:, :])
    end = compose_torch(start, local[..., -1, :])
    return torch.cat([hermite_frames(before, start, end), end[..., None, :]], -2)


def candidate_frames(kind: torch.Tensor, pose: torch.Tensor, before: torch.Tensor, token_poses: torch.Tensor, r: torch.Tensor,
                     tok: torch.Tensor, interpolation: str = "spline") -> torch.Tensor:
    """[R, c, 5, 3]: the step's frames of rows ``r`` [R] (of M agents of types ``kind`` [M], at ``pose`` from ``before``
    [M, 3]) were they to take tokens ``tok`` [R, c] of ``token_poses`` [types, V, 6, 3], placed as the step places them
    (:func:`token_frames`): the candidates a search over tokens tests."""
    local = token_poses[kind[r][:, None], tok]  # [R, c, 6, 3]
    c = tok.shape[1]
    return token_frames(local, pose[r][:, None].expand(-1, c, -1), before[r][:, None].expand(-1, c, -1), interpolation)


def hermite_frames(before: torch.Tensor, start: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
    """The 4 in-between 10 Hz poses [..., 4, 3] of a token from pose ``start`` to pose ``end`` [..., 3]:
    a cubic Hermite curve in x, y and heading whose tangents are ``start - before`` (the previous
    token's displacement; the token's own where ``before`` is NaN) and ``end - start``, so that
    consecutive tokens join with continuous velocity and yaw rate. The start tangent is capped at
    ``MAX_LEAD`` times the token's displacement (position and heading separately) so that the curve
    never overshoots its end. Headings are unwrapped along the way and wrapped back."""
    chord, lead = end - start, start - before
    chord[..., 2:] = wrap_angle(chord[..., 2:])
    lead[..., 2:] = wrap_angle(lead[..., 2:])
    lead = torch.where(torch.isnan(lead), chord, lead)
    # no overshoot: a tangent at most 2.8x the token's own displacement (the Fritsch-Carlson bound for
    # a monotone cubic), in position and in heading, so that a token that stops or stops turning
    # does not first run on and come back
    limit_xy = MAX_LEAD * chord[..., :2].norm(dim=-1, keepdim=True)
    lead_xy = lead[..., :2] * (limit_xy / lead[..., :2].norm(dim=-1, keepdim=True).clamp(min=1e-9)).clamp(max=1.0)
    cap_h = MAX_LEAD * chord[..., 2:].abs()
    lead_h = torch.maximum(torch.minimum(lead[..., 2:], cap_h), -cap_h)
    lead = torch.cat([lead_xy, lead_h], -1)
    h10, h01_plus_h11 = _hermite_basis(start.device, start.dtype)
    out = start[..., None, :] + h10 * lead[..., None, :] + h01_plus_h11 * chord[..., None, :]
    out[..., 2:] = wrap_angle(out[..., 2:])
    return out


_BASIS: dict = {}


def _hermite_basis(device, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """The Hermite basis at the in-between frames, (4, 1) each: ``h10`` (the start tangent's) and
    ``h01 + h11`` (the end point's and the end tangent's, which is the chord itself); computed once per
    device and dtype."""
    key = (str(device), dtype)
    if key not in _BASIS:
        s = _HERMITE_S.to(device, dtype)[:, None]
        _BASIS[key] = (s**3 - 2 * s**2 + s, 2 * s**2 - s**3)
    return _BASIS[key]


def compose_torch(origin: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
    """Poses ``local`` [..., 3] in the frame of ``origin`` [..., 3] -> outer frame (heading wrapped)."""
    c, s = origin[..., 2].cos(), origin[..., 2].sin()
    x = origin[..., 0] + c * local[..., 0] - s * local[..., 1]
    y = origin[..., 1] + s * local[..., 0] + c * local[..., 1]
    h = wrap_angle(origin[..., 2] + local[..., 2])
    return torch.stack([x, y, h], -1)
