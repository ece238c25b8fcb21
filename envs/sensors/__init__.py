"""Simulated sensors (numpy + MuJoCo only): the Digit 360 fingertip (`digit360`, `digit360_render`,
`tactile_obs`) and the Kaldi filterbank its audio windows need (`kaldi`)."""
