"""Touch encoders and their jobs, by role.

    models/    Sparsh-X and Sparsh-skin: inputs, tokenizers, blocks, the token interface, pooling, the registry
    ssl/       the self-distillation pieces shared by both encoders (masking, DINO/iBOT losses, schedules)
    pretrain/  `rotate pretrain`: config, objectives, saved state, logs, the job
    probes/    `rotate probe`: data, skin decoders, report, the job
    loading.py the touch windows both jobs read; runtime.py, what they share at run time (devices, precision);
    encoder_info.py, `rotate encoder-info`
"""
