"""Self-supervised pieces shared by the touch encoders (Sparsh-X now, Sparsh-skin later), generic over token sets:
block masking into views (`masking`), the DINO head and loss with per-set centering (`dino`), and the schedules,
EMA teacher update and optimizer groups (`schedules`)."""

from rotation.tactile.ssl.dino import DINOHead, DINOLoss, teacher_entropy
from rotation.tactile.ssl.masking import MaskConfig, block_shape, sample_set_views, sample_views, step_rng
from rotation.tactile.ssl.schedules import (
    cosine,
    ema_momentum,
    ema_update,
    param_groups,
    set_hyperparameters,
    teacher_temperature,
    warmup_cosine,
)

__all__ = [
    "DINOHead", "DINOLoss", "MaskConfig", "block_shape", "cosine", "ema_momentum", "ema_update", "param_groups",
    "sample_set_views", "sample_views", "set_hyperparameters", "step_rng", "teacher_entropy", "teacher_temperature",
    "warmup_cosine",
]
