"""Tile encoders, structure-aware tile/chip descriptors and the FAISS-HNSW covisibility index."""

from vggt_slam_pp.retrieval.descriptors import aggregate, cell_weights
from vggt_slam_pp.retrieval.encoders import DinoV2Encoder, Encoder, HogEncoder, make_encoder
from vggt_slam_pp.retrieval.index import CovisibilityEdge, IndexConfig, TileIndex

__all__ = ["CovisibilityEdge", "DinoV2Encoder", "Encoder", "HogEncoder", "IndexConfig", "TileIndex", "aggregate",
           "cell_weights", "make_encoder"]
