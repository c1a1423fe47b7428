"""Preprocessing (chapter §8.5): each stage on its own, and the `Preprocessor` that chains them."""

from facerec3d.preprocess.denoise import DenoiseConfig, denoise
from facerec3d.preprocess.detect import DetectConfig, Detection, crop_sphere, detect_face
from facerec3d.preprocess.holes import HoleConfig, fill_holes, hole_mask
from facerec3d.preprocess.pipeline import PreprocessConfig, Preprocessor, landmarks_in_input_frame
from facerec3d.preprocess.resample import ResampleConfig, depth_map, gridify, resample
from facerec3d.preprocess.spikes import SpikeConfig, remove_spikes, spike_mask

__all__ = [
    "DenoiseConfig", "DetectConfig", "Detection", "HoleConfig", "PreprocessConfig", "Preprocessor",
    "ResampleConfig", "SpikeConfig", "crop_sphere", "denoise", "depth_map", "detect_face", "fill_holes",
    "gridify", "hole_mask", "landmarks_in_input_frame", "remove_spikes", "resample", "spike_mask",
]
