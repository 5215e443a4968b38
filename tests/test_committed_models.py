"""Every model committed under models/ loads, plays and exports exactly as it did before MAgent
training was added: the digests below were made with that code (commit 92dec93). A model
retrained since has the digests of the code it was committed with (``hidden_goal``: 88b82d8;
``find_water``: trained at 2ee4a88, its earlier model kept in ``find_water/minmax``; on the small
evaluation here the two play the same episodes to the same scores, their exports differ;
``surround`` and ``baselines/surround_*``: trained at cc808f3; ``magent_pursuit``: at 0a41569;
``baselines/magent_pursuit_iql``: at 092e8d6; ``magent_tiger``: at 38700d9;
``baselines/magent_pursuit_vdn``, ``baselines/magent_pursuit_qmix``,
``baselines/magent_pursuit_coma``, ``baselines/magent_tiger_vdn``,
``baselines/magent_tiger_qmix``, the further training seeds
``baselines/magent_tiger_qmix/seed1``, ``baselines/magent_tiger_qmix/seed2`` and
``magent_tiger/seed1``, ``magent_queue``, its try at N = 2-20 ``magent_queue/agents2_20``,
``baselines/magent_queue_qmix`` and ``baselines/magent_queue_vdn``: at 9fa5f8f; the pursuit tries
on a 30×30 map ``baselines/magent_pursuit_iql/map30``, ``baselines/magent_pursuit_vdn/map30``,
``baselines/magent_pursuit_qmix/map30`` and ``magent_pursuit/map30``: at 01c9298;
``magent_pursuit/map30_sum``, ``magent_pursuit/map30_sum15`` and its second training seed
``magent_pursuit/map30_sum15/seed1``: at 5dff52b; the further training seeds
``magent_pursuit/map30_sum15/seed2``, ``baselines/magent_pursuit_iql/map30/seed1`` and
``seed2``: at 065d8a3; the queue learners shaped toward the line ``magent_queue/shaped``,
``baselines/magent_queue_qmix/shaped`` and ``baselines/magent_queue_vdn/shaped``, and QMIX,
VDN and UDAN shaped at the full budget ``baselines/magent_queue_qmix/shaped_2m``,
``baselines/magent_queue_vdn/shaped_2m`` and ``magent_queue/shaped_2m``: at 4887bcc;
IQL trained at N = 10 and 20 on the 30×30 schedule ``baselines/magent_pursuit_iql/map30_n10``
and ``map30_n20``, and UDAN's third tiger seed ``magent_tiger/seed2``: at 065d8a3).
Exports of UDAN models have the digests of the exporter that folds the leader attention's
weights in float64 (since find_water's retraining): folded in float32, their last bits, and so
the digests, depended on the machine's BLAS kernels (two machines of this project disagreed)."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch

from udan.checkpoint import load_model
from udan.evaluate import CheckpointPolicy, evaluate
from udan.export.graph import build_graph
from udan.export.metadata import build_metadata

MODELS = Path(__file__).resolve().parents[1] / "models"
#: checkpoint folder -> (sha256 of its per-episode scores in a small evaluation, sha256 of the
#: ONNX file exported from it)
BEFORE = {
    "baselines/find_water_coma": (
        "ac2dde33cc1af75d8b736ecd0d8655f9ea2b111aa9f88d3f5d217e6303fd672b",
        "34107cc944c2c08b46184f09857fbf809d03e1b6da225a8e5eb884394173cf88",
    ),
    "baselines/find_water_iql": (
        "f47d851d62b718ab6116437c664787275c6815137ed4a5ef947e96cd540201f2",
        "abae27f5fcd45dc45a4cc780f47b3f5e46cdb998bda2dd30b87e9b9a359b7973",
    ),
    "baselines/find_water_qmix": (
        "94eb77668b7cf552651ea695722ec7c68e84eaee692c582080bb8ce35904fc8d",
        "d90fdea9c03bf00cd23751de66efed4b25c66d8525905931f3c6ea073303b143",
    ),
    "baselines/find_water_vdn": (
        "608e267864379f879e30c210bccb5f5d6fa67ab0784e39976e36828cf9e83b35",
        "16f1f76169d213d017a6f96deb77f28d8211b81a30c7a09ccc7e92c9414dea67",
    ),
    "find_water": (
        "43cdf626a99dd94ee2e6299808980431fbfdd208e3610a798303f23a2d315914",
        "f95877b205031b571371243b78ae81eae4220533f35bae2b6fa9a7a179c5030e",
    ),
    "find_water/minmax": (
        "43cdf626a99dd94ee2e6299808980431fbfdd208e3610a798303f23a2d315914",
        "4f09bc6478c7a1b4d25cc39cc1fd325670871e8a5a268db5adfa7a3b80d702dc",
    ),
    "hidden_goal": (
        "f97411750d28ba26cd268612ce66bc2e3cd15c7bb4b65d169e0ea4a4f2120dc2",
        "41a9dfd26d4a2ebb4e1ebf07f74beda9193073bef6d572b9dd1a576483f083fd",
    ),
    "hidden_goal/minmax": (
        "00469081085ac973045309713b502255bc98d6a0cce02d00eeb4da1991dd7268",
        "e49fc056ac105439436b4c62a328e1c8f94f9b895bde4fa65a457971750f3ed7",
    ),
    "hidden_goal/iql": (
        "db3d64315937200a65aa4421b8f9e4a5e8d7b49aa0d2605366cdd52d80b11802",
        "4d76386ced44b7941d5b9961aa12deee32194e1a5817601cbddaffe906a13a6c",
    ),
    "hidden_goal/no_messages": (
        "f87ca86a8ca1637691df7cf72adc42a97af29877964175f6844797669e578510",
        "30bb0ccb9d6944f25b25e4b7e01940f1190e76a906fe9795c353435581865a9b",
    ),
    "surround": (
        "c2715a2d4fc42743dd76225ff94d450c032d4e2011e2f41c9f4fa378a85de46f",
        "23ea9ddb85184b541a88c560b1bcc40874f87bc186179b3a3aecb63a08d86a73",
    ),
    "baselines/magent_pursuit_coma": (
        "2d5565fb483d8ea4525a7a9229677d1038ad34b6e22c8d5152e1d7f7b9817597",
        "ac38ff0caad90584a7881577fd1efa48b454cbd78cadf88c511003974c67d8d7",
    ),
    "baselines/magent_pursuit_iql": (
        "2d5565fb483d8ea4525a7a9229677d1038ad34b6e22c8d5152e1d7f7b9817597",
        "cba476b48fe0a9e5705e9412b08678f9d6e05fbb8d0c369577057218134352c7",
    ),
    "baselines/magent_pursuit_iql/map30": (
        "116a6e8614810d97b0c779cdcaa7189c440246e784e690b89b64d2ff701bb2f2",
        "d44af6a97bfddc4c4a567ac35e683f8bd63f3b3e4459fcd8f0dc8e21e2ed442e",
    ),
    "baselines/magent_pursuit_iql/map30_n10": (
        "8247346fdf436bc4c54217e7c05e4c145782edfde64b9e0bd342eff5b2334990",
        "4e9d303cc68e9426af51ccdac6fde1997676591a7e3e1d76597845ae4208db32",
    ),
    "baselines/magent_pursuit_iql/map30_n20": (
        "14509ce0143993f71575b65b48671e7f14bcfeccd9b9d5cc94dd6e34759662d1",
        "526e546536996d4b3954d9f7782dc0e631664e0b70b90fa582848dbe064dd97c",
    ),
    "baselines/magent_pursuit_iql/map30/seed1": (
        "36cc8d6cacfa123c8819c3daa38177bb4ec97a2a2563ddfa88d5e07ebac2709b",
        "9e272ca606a5055cb728ed06174c82736c3cc5f03e0292fa6cd63bdadce462c0",
    ),
    "baselines/magent_pursuit_iql/map30/seed2": (
        "92a525bf7efde187f018a1f8989ae53e472802799d8482ec0a99e015a0d5fc75",
        "bd8f76ab3bf85e8f2189e28c3442772f822e125240eb5d5e157d125995ede967",
    ),
    "baselines/magent_pursuit_qmix": (
        "2d5565fb483d8ea4525a7a9229677d1038ad34b6e22c8d5152e1d7f7b9817597",
        "fa40fa54fb97d6a79a5879ac0dae2c97ff376bb86911bfc0e6067aa0d673c411",
    ),
    "baselines/magent_pursuit_qmix/map30": (
        "2f28546f6b891553aec80663da0a913ec63068b60239db86e1ad3e2b491a076d",
        "a970300573fb063bffad5deea90f9efad2684f3e651124408733a595a4829a5e",
    ),
    "baselines/magent_pursuit_vdn": (
        "2d5565fb483d8ea4525a7a9229677d1038ad34b6e22c8d5152e1d7f7b9817597",
        "d640a65ab3f9a3c467c224434f313a984024043a070f64f809901cdcd1a0a329",
    ),
    "baselines/magent_queue_qmix": (
        "4cb0bdbbbf095942a8619c2274ea221226a3dccbf10f4cb1570ee81fab1f199b",
        "2f1149ddcf47aaecd8eaa73821d3fbab1848d26751674d9e5b9d592c2636457e",
    ),
    "baselines/magent_queue_vdn": (
        "73608d60daac8cb9f3063d9f0619f9debf7718451d90f5f8d8508d916eb18c44",
        "d1f4af7b53af565925b72432f0067398f589874a32e95f691f4d1e8101991c93",
    ),
    "baselines/magent_queue_qmix/shaped": (
        "cb8aa389fab1f4d9823bf8d6d8d04b2560219227d7756031f8e106fe62d24ff1",
        "5eedc6805c52ad14277372dd3c964aafd5f57f431cb7bc2355eb506368b4b111",
    ),
    "baselines/magent_queue_qmix/shaped_2m": (
        "5e44327ced5217a5d9733b9b6189fb819976105c9e4532350a37049c4531d1b3",
        "330bcef04f5f1266c458173de7ae3c6f64933f45c8a40e1cd68a484037dc27b6",
    ),
    "baselines/magent_queue_vdn/shaped": (
        "b5ad378514e99895a700b08f6f8e6a5de958d2fbeeb40208f56b8525a4c1e933",
        "70c5febac27a044b59cabd6335798a7b54edf179b8b138fc4d395c9f169fea95",
    ),
    "baselines/magent_queue_vdn/shaped_2m": (
        "10d2b5bec0f86a23c7f589ba5896898e28f8dafe8078f3890b236715b3fa6d55",
        "b5058624d2b06c835ca8f19dc680da539e4021bfc37f2d9e6556ceff55005829",
    ),
    "baselines/magent_tiger_qmix": (
        "d30bd04a98043abef895e0ff86993cb56eba29eea5bf015c1b62b46031188137",
        "d3949d5f88dffd85346f8fa4f8a89b93f7d950e62b28bab66eab88053ddc42cb",
    ),
    "baselines/magent_tiger_qmix/seed1": (
        "6f5adb517b7428100f0b8f503e8e387fa9fc4a90e0026b5fbbb1210451012007",
        "ec19394ef04a983232533c3ae448d92422bd28773d93725eaa4d2b7e74b65388",
    ),
    "baselines/magent_tiger_qmix/seed2": (
        "652c9ff2ccebe749ed35fcc64deb56a10b90c56859b7a074fe5ad272dfe11da8",
        "f45c0265fb2f571f8bcb622a9d412f759aa70afee041aaded7a1ee78c3fbe776",
    ),
    "baselines/magent_tiger_vdn": (
        "3d1b2ef86d0e05f0a91e5e906cb901ef6cf405fbbffac174286337937e2878ff",
        "c346346e33e6a67e4cf8a6bfc17041b2e9ef82ba1b70903b4f5bbb3b31920275",
    ),
    "baselines/surround_coma": (
        "1982f63619f7bef84e61ce0f974f29795ae139239308a56f969c0b5e99cd8926",
        "69c6ba5c82570f4a11207f41391f2d2fd7b2ddf8e979443b753002ff042c6d4a",
    ),
    "baselines/surround_iql": (
        "7fa6cb7070ae186eccf9812b578c4c5d8fee493a7ff109e1529170536454bf96",
        "eb2c4891da8fc923c41d8e9b2a14cc28bed52583b20775511de8b0cfaddb74a7",
    ),
    "baselines/surround_qmix": (
        "53e9c327e114e58bdcbc13c000d56b70b8dcab01888905edac9bfd12a9105750",
        "17a11bf235305dae9c41b664a50e95cb7e4ba6e0c35422cfcae522e57b47921b",
    ),
    "baselines/surround_vdn": (
        "2782148e79acb10fcff62e1dd4771bade2128483a11b5acccdc0869117d25cbe",
        "6a1c8be788bdd9a1f6d3effcc3ff5341037776903c6aaf09831c8ebccf08e1fe",
    ),
    "baselines/magent_pursuit_vdn/map30": (
        "2d5565fb483d8ea4525a7a9229677d1038ad34b6e22c8d5152e1d7f7b9817597",
        "e83cb362e54e76c9b1e0aff8858018f5f5fa9f996279abeeff92dfe28a85e226",
    ),
    "magent_pursuit": (
        "2d5565fb483d8ea4525a7a9229677d1038ad34b6e22c8d5152e1d7f7b9817597",
        "26f358777635dacfc64c6e7de64e1ca594bdd4219b821e3cecd7096f1954bfd1",
    ),
    "magent_pursuit/map30": (
        "2d5565fb483d8ea4525a7a9229677d1038ad34b6e22c8d5152e1d7f7b9817597",
        "1651a7d04d6fb42b8d3a48c3f5cfb6a4166b6eeab45f1aa577a29811f3c38e04",
    ),
    "magent_pursuit/map30_sum": (
        "2d5565fb483d8ea4525a7a9229677d1038ad34b6e22c8d5152e1d7f7b9817597",
        "e29c7256ccd9fadc8521ce78b6472fbaca8ae9bb1b8a4718b5084e8ab1f3f216",
    ),
    "magent_pursuit/map30_sum15": (
        "728c396a6beaff8c8446d35247fc206f00a7177199625c483a68b5d3d74633ce",
        "86ba5f1f9a337ca55003c2720f928f96d3a6123c7ab67768fecce71c9df21cc7",
    ),
    "magent_pursuit/map30_sum15/seed1": (
        "125706b7c4aec7859bb383370bc9786f657e6d69509f352627978ee8411741c6",
        "21e36fbcb911b10d479fbd5cb5d32d7977ddcecb670140b013e72fcdd76397be",
    ),
    "magent_pursuit/map30_sum15/seed2": (
        "ea77d06d210029d2398f762411e471300d3cb2eb28d7aee3eec89aa77fc9ebd5",
        "fd10200584fb3a72ebafdbed15484b6d6217b9958df34b9be21399907e566b17",
    ),
    "magent_queue": (
        "abf552fd0715c7bee620d228eca29504ff47e14353af293adc88277a0ec5d83d",
        "f6bfe13cbf6b7af045c47020bb557531a0da950eedeb6bbf989406136b7ffc96",
    ),
    "magent_queue/agents2_20": (
        "c10279ff66498ec6164e44627c5565f0f32a95bfc81122d99ebad1684bb26667",
        "2c4dae05c074ac962cc91edf326bb9ec6b472707fa018d6d9221330418899414",
    ),
    "magent_queue/shaped": (
        "86fd320fcafe9f6b3f373d7e46972c71dc1e1ade25dce00f89abfa9d200ba6f1",
        "71b463b18a1addbd17daec39815ec3858c5101426608d1803a691aa900ba8c09",
    ),
    "magent_queue/shaped_2m": (
        "3b70bff3e43c6dd1085394ac59322e25e75e81fe02e91454979ab9e7862619cb",
        "c4bb913b4ba26ad61451a12807d1e2af81de2424117b69be2c33cd1b09cf0cd5",
    ),
    "magent_tiger": (
        "d6ab7da2424be1df56d52ceb79d46452c041947cbb464e17de54815df11dec39",
        "2a2be4d2aff5545df8b862cdc6f30f9178d23aa358256c69814628f7cc1b8dee",
    ),
    "magent_tiger/seed1": (
        "2d5565fb483d8ea4525a7a9229677d1038ad34b6e22c8d5152e1d7f7b9817597",
        "2e8df99352ab1f9ef996b21f8f7df2630ac40633789a312a20581e6aa7144737",
    ),
    "magent_tiger/seed2": (
        "95cd32f75af82d3c582e841a97510d7d14525d1890377041ee1cf7d5a16daa00",
        "e98ce55df12df866a4b2478eccf759e618550e65c9fca8b7a58f4ad80bcb994a",
    ),
}


def test_every_committed_checkpoint_is_listed():
    found = {str(p.parent.relative_to(MODELS)) for p in MODELS.rglob("checkpoint.pt")}
    assert found == set(BEFORE)


@pytest.mark.parametrize("folder", sorted(BEFORE))
def test_a_committed_model_plays_and_exports_as_before(folder):
    torch.set_num_threads(1)
    path = MODELS / folder / "checkpoint.pt"
    model, ckpt = load_model(path)
    hidden_goal = ckpt["env"] == "arena/hidden_goal"
    agents, obstacles = ((2, 3), (0, 0)) if hidden_goal else ((1, 3), (0, 1))
    results = evaluate(ckpt["env"], CheckpointPolicy(model), agents, obstacles, 6, 0)
    scores = np.concatenate([r.scores for r in results]).astype(np.float64)
    assert hashlib.sha256(scores.tobytes()).hexdigest() == BEFORE[folder][0]

    checkpoint_sha = hashlib.sha256(path.read_bytes()).hexdigest()
    meta = build_metadata(ckpt, dataclasses.asdict(model.spec), checkpoint_sha)
    assert meta.pop("agents") == str(ckpt["config"]["agents"])  # the one entry added since
    exported = build_graph(model, meta).SerializeToString()
    assert hashlib.sha256(exported).hexdigest() == BEFORE[folder][1]
