"""Runtime for user-supplied ONNX landmark detectors (schema: ``docs/detector_spec.md``).

* :mod:`.spec` parses and validates the JSON spec (versions 1 and 2); :mod:`.session` checks it against
  the model; :mod:`.decode` turns the outputs of any described layout into positions (coordinates in
  any order, heatmaps, logits, SSD / BlazeFace anchors and NMS; pure numpy).
* :mod:`.crop` holds the crop geometry (pure functions, OpenCV pixel centres).
* :mod:`.finder` finds the face without a track (Haar cascade, full frame, or a face-detector ONNX).
* :mod:`.runtime` runs the model on crops in batches and tracks (:class:`Detector`).
* :mod:`.pipeline` runs a whole video with an on-disk cache (:func:`detect_video`).
* :mod:`.standalone` is ``capture detect`` (with :mod:`.summary`: faces, confidence, jitter; and
  :mod:`.overlay`: drawing).
* :mod:`.embedding` reads and writes the per-actor landmark embeddings; :mod:`.embed` makes them from
  vertex ids, triangles, points or a canonical mesh; :mod:`.refine` refines one on footage;
  :mod:`.embed_actor` is ``capture actor embed``.
* :mod:`.synthetic` builds small ONNX models with known behaviour (tests, benchmarks).
"""

from capture.detector.crop import Crop
from capture.detector.embedding import (LandmarkEmbedding, embedded_points, embedding_from_points,
                                        embedding_from_vertices, read_embedding, write_embedding)
from capture.detector.pipeline import LandmarkTrack, detect_video
from capture.detector.runtime import Detector, FrameLandmarks, TrackOptions, TrackState
from capture.detector.spec import DetectorSpec, load_detector_spec, parse_detector_spec

__all__ = ["Crop", "Detector", "DetectorSpec", "FrameLandmarks", "LandmarkEmbedding", "LandmarkTrack",
           "TrackOptions", "TrackState", "detect_video", "embedded_points", "embedding_from_points",
           "embedding_from_vertices", "load_detector_spec", "parse_detector_spec", "read_embedding",
           "write_embedding"]
