//! The physics commands end to end through the CLI, and their errors.

use crate::common::*;

#[test]
fn psf_blur_map_and_dataset_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let d = |p: &str| dir.path().join(p).to_str().unwrap().to_string();
    let r = cli(&["psf", "simulate", "--lens", "calib/lens_single_lwir.yaml", "-o", &d("psf"), "--grid", "3x4", "--kernel", "21"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    for f in ["psfs.npy", "psf.yaml", "montage.png"] {
        assert!(dir.path().join("psf").join(f).is_file(), "{f}");
    }
    let r = cli(&["psf", "blur-map", &d("psf"), "-o", &d("blur")]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let map = pdi_compile::optics::blur_map::BlurMap::load(&dir.path().join("blur.yaml")).unwrap();
    assert_eq!((map.rows, map.cols), (3, 4));
    let npy = pdi_compile::optics::blur_map::BlurMap::load(&dir.path().join("blur.npy")).unwrap();
    assert_eq!(map.values, npy.values);
    let r = cli(&["dataset", &d("set"), "--psf", &d("psf"), "--n", "3", "--size", "160x120", "--q", "10"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(r.stdout.contains("PSNR"), "{}", r.stdout);
    for sub in ["clean", "degraded"] {
        let n = std::fs::read_dir(dir.path().join("set").join(sub)).unwrap().filter(|e| e.as_ref().unwrap().path().extension().is_some_and(|x| x == "png")).count();
        assert_eq!(n, 3, "{sub}");
    }
    assert!(dir.path().join("set/degraded/000000.txt").is_file(), "labels travel with degraded frames");
    let (w, h, _) = pdi_compile::frames::read_gray(&dir.path().join("set/degraded/000002.png")).unwrap();
    assert_eq!((w, h), (160, 120));
}

#[test]
fn physics_commands_reject_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let lens = dir.path().join("lens.yaml");
    std::fs::write(&lens, "name: x\nf_number: 1\nfocal_length_mm: 70\npixel_um: 12\nsensor: [640, 480]\nwavelengths_um: [10]\naberrations: {}\n").unwrap();
    let r = cli(&["psf", "simulate", "--lens", lens.to_str().unwrap(), "-o", dir.path().join("o").to_str().unwrap()]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("at least 5 wavelengths"), "{}", r.stderr);
    let r = cli(&["degrade", "calib", dir.path().join("o").to_str().unwrap(), "--psf", dir.path().to_str().unwrap(), "--q", "10"]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("psf simulate"), "{}", r.stderr);
    let r = cli(&["synth", dir.path().join("s").to_str().unwrap(), "--size", "640by480"]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("--size"), "{}", r.stderr);
    let r = cli(&["dataset", dir.path().join("d").to_str().unwrap(), "--psf", "calib", "--q", "0"]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("--q"), "{}", r.stderr);
}
