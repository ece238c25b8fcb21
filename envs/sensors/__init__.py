"""Simulated sensors (numpy + MuJoCo only): the Digit 360 fingertip (`digit360`, `digit360_render`,
`tactile_obs`) and the Kaldi filterbank its audio windows need (`kaldi`); the Xela skin of the whole hand
(`xela_layout`, `xela` numpy only; `xela_hand` the hand variant and its MuJoCo sensors; `skin_obs` the env's group)."""
