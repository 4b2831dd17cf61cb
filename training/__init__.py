"""cmnav training: the CMWAE encoder and the recurrent PPO policy."""
