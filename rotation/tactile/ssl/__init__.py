"""Self-supervised pieces shared by the touch encoders (Sparsh-X and Sparsh-skin), generic over token sets: block
masking into views (`masking`: Sparsh-X's one global + local blocks, DINOv2-style global/local views with iBOT
masks), the DINO head and loss with per-set centering, the iBOT masked-token loss and the KoLeo regularizer
(`dino`), and the schedules, EMA teacher update and optimizer groups (`schedules`)."""

from rotation.tactile.ssl.dino import DINOHead, DINOLoss, IBOTLoss, koleo_loss, teacher_entropy
from rotation.tactile.ssl.masking import (
    MaskConfig,
    ViewMaskConfig,
    Views,
    block_shape,
    sample_multi_views,
    sample_set_views,
    sample_views,
    step_rng,
)
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
    "DINOHead", "DINOLoss", "IBOTLoss", "MaskConfig", "ViewMaskConfig", "Views", "block_shape", "cosine",
    "ema_momentum", "ema_update", "koleo_loss", "param_groups", "sample_multi_views", "sample_set_views",
    "sample_views", "set_hyperparameters", "step_rng", "teacher_entropy", "teacher_temperature", "warmup_cosine",
]
