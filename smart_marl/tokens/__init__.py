"""Tokens stage: motion tokens (k-disks vocabularies of 0.5 s snippets, rolling matching,
detokenization) and road-vector tokens (5 m road pieces, their vocabulary and topology sequences).

Scenario -> :func:`tokenize_motion` -> :class:`MotionTokens` (what the SMART model trains on and
the environment acts in) and Scenario -> :func:`road_pieces` / :func:`tokenize_road` ->
:class:`RoadTokens` (RoadNet's input and the road next-token task). Vocabularies are versioned
files (:mod:`.vocab_io`) that checkpoints refer to by content hash.
"""

from .kdisks import KDisksResult, kdisks, mean_point_distance
from .motion import (
    BOX_SIZE_M, FRAMES_PER_TOKEN, MOTION_TYPES, POSES_PER_TOKEN, TOKEN_S, TYPE_KEYS, MotionTokens, MotionVocabulary, TypeVocab,
    augment_snippets, box_contour, build_motion_vocabulary, collect_snippets, compose_poses, detokenize, place_tokens,
    reconstruct, relative_poses, snippets_from_tracks, token_boundaries, token_poses_from_contours, tokenize_motion,
    tokenize_tracks, uniform_grid_vocabulary,
)
from .road import (
    MAX_PIECE_LENGTH_M, PIECE_POINTS, RoadPieces, RoadVocabulary, build_road_vocabulary, match_road_pieces, road_pieces,
    road_successor_pairs, sample_road_walks,
)
from .vocab_io import (
    VocabularyFileError, load_motion_vocabulary, load_reference_motion_vocabulary, load_road_vocabulary,
    save_motion_vocabulary, save_road_vocabulary,
)
