"""Touch encoders (Sparsh-X, Sparsh-skin) and their input features (`audio`: the Kaldi log-mel filterbank)."""
