//! The physics pipeline: diffraction, blur factors, degradation, the blur-map upsample, scenes.

use crate::common::repo;
use pdi_compile::optics::blur_index::{blur_map, resize_half_pixel, spot_stats};
use pdi_compile::optics::degrade::{add_noise, psnr, NoiseModel, SpatialBlur, FULL_SCALE_14BIT};
use pdi_compile::optics::lens::{Aberrations, FieldAberrations, Lens};
use pdi_compile::optics::psf::{psf_kernel, psf_oversampled, simulate};
use pdi_compile::optics::rng::Rng;
use pdi_compile::optics::synth;
use pdi_compile::onnx::proto::*;
use pdi_compile::runtime::{self, Engine};
use pdi_compile::tensor::{Tensor, TensorData};

fn ideal_lens() -> Lens {
    Lens {
        name: "ideal".into(),
        description: String::new(),
        f_number: 1.5,
        focal_length_mm: 70.0,
        pixel_um: 12.0,
        sensor: [640, 480],
        wavelengths_um: vec![8.0, 9.0, 10.0, 11.0, 12.0],
        aberrations: Aberrations::default(),
    }
}

#[test]
fn aberration_free_pupil_gives_an_airy_pattern() {
    let lens = ideal_lens();
    for lambda in [8.0, 10.0, 12.0] {
        let (psf, m, dx) = psf_oversampled(&lens, lambda, &FieldAberrations::default(), 0.0);
        assert!((psf.iter().map(|&v| v as f64).sum::<f64>() - 1.0).abs() < 1e-5);
        // Radial profile in bins of dx / 4 around the centre sample.
        let bin = dx / 4.0;
        let nb = (m as f64 * dx / 2.0 / bin) as usize;
        let (mut sum, mut cnt) = (vec![0f64; nb], vec![0usize; nb]);
        let c = (m / 2) as f64;
        for y in 0..m {
            for x in 0..m {
                let r = ((x as f64 - c).hypot(y as f64 - c)) * dx;
                let b = (r / bin) as usize;
                if b < nb {
                    sum[b] += psf[y * m + x] as f64;
                    cnt[b] += 1;
                }
            }
        }
        let prof: Vec<f64> = sum.iter().zip(&cnt).map(|(s, &n)| if n > 0 { s / n as f64 } else { f64::NAN }).collect();
        let expected = 1.22 * lambda * lens.f_number;
        // First local minimum after the peak.
        let first_min = (2..nb - 2).find(|&i| prof[i].is_finite() && (i - 1..=i + 1).all(|j| prof[j].is_nan() || prof[i] <= prof[j]) && prof[i] < prof[0] * 0.05).unwrap();
        let found = (first_min as f64 + 0.5) * bin;
        assert!((found - expected).abs() <= 0.25 * lens.pixel_um, "lambda {lambda}: dark ring at {found:.2} um, Airy says {expected:.2} um");
    }
}

#[test]
fn every_kernel_sums_to_one_and_blur_grows_with_defocus() {
    let lens = ideal_lens();
    let mut last = 0.0;
    for defocus in [0.0, 0.5, 1.0, 2.0, 4.0] {
        let k = psf_kernel(&lens, &FieldAberrations { defocus, ..Default::default() }, 0.0, 31);
        assert!((k.iter().map(|&v| v as f64).sum::<f64>() - 1.0).abs() < 1e-5);
        let r = spot_stats(&k, 31).rms_radius;
        assert!(r > last, "defocus {defocus}: RMS radius {r} not above {last}");
        last = r;
    }
}

#[test]
fn single_lens_corners_are_blurrier_than_its_centre_and_the_reference_is_flat() {
    for (file, single) in [("calib/lens_single_lwir.yaml", true), ("calib/lens_multi_lwir.yaml", false)] {
        let lens = Lens::load(&repo().join(file)).unwrap();
        let (_, kernels) = simulate(&lens, 6, 8, 31);
        for k in &kernels {
            assert!((k.iter().map(|&v| v as f64).sum::<f64>() - 1.0).abs() < 1e-5);
        }
        let stats: Vec<_> = kernels.iter().map(|k| spot_stats(k, 31)).collect();
        let map = blur_map(&stats, 6, 8);
        let (corner, centre) = (stats[0].rms_radius, stats[3 * 8 + 3].rms_radius);
        if single {
            assert!(corner > 1.5 * centre, "{file}: corner {corner:.2} px vs centre {centre:.2} px");
            assert!(map.values[0] > 0.9 && map.values[3 * 8 + 3] < 0.1, "{:?}", map.values);
        } else {
            assert!(corner < 1.1 * centre, "{file}: corner {corner:.2} px vs centre {centre:.2} px");
            assert!(map.values.iter().all(|&v| v < 0.1), "a near diffraction-limited camera has a flat map: {:?}", map.values);
        }
    }
}

fn single_lens_blur(h: usize, w: usize) -> SpatialBlur {
    let lens = Lens::load(&repo().join("calib/lens_single_lwir.yaml")).unwrap();
    let (_, kernels) = simulate(&lens, 6, 8, 31);
    SpatialBlur::new(&kernels, 31, 6, 8, h, w)
}

#[test]
fn degrading_a_constant_image_keeps_it_constant_and_noise_matches_q_and_sigma() {
    let (h, w) = (240, 320);
    let blur = single_lens_blur(h, w);
    let out = blur.apply(&vec![0.4f32; h * w]);
    let worst = out.iter().map(|&v| (v - 0.4).abs()).fold(0f32, f32::max);
    assert!(worst < 1e-5, "constant image changed by {worst}");
    for (q, sigma) in [(10.0, 2.0), (90.0, 2.0), (90.0, 0.5)] {
        let mut img = vec![0.4f32; h * w];
        add_noise(&mut img, &NoiseModel { q, sigma, full_scale: FULL_SCALE_14BIT }, &mut Rng::new(3));
        let counts: Vec<f64> = img.iter().map(|&v| v as f64 * FULL_SCALE_14BIT).collect();
        let mean = counts.iter().sum::<f64>() / counts.len() as f64;
        let std = (counts.iter().map(|c| (c - mean).powi(2)).sum::<f64>() / counts.len() as f64).sqrt();
        let want_mean = (0.4 * FULL_SCALE_14BIT / q).floor() * q;
        assert!((mean - want_mean).abs() < 3.0 * sigma * q / (counts.len() as f64).sqrt() + 1e-3, "q {q}: mean {mean} vs {want_mean}");
        assert!((std / (sigma * q) - 1.0).abs() < 0.02, "q {q} sigma {sigma}: std {std} vs {}", sigma * q);
    }
}

#[test]
fn low_snr_is_noisier_than_high_snr_and_blur_has_no_seams() {
    let (h, w) = (480, 640);
    let scene = synth::scene(w, h, 11);
    let blur = single_lens_blur(h, w);
    let blurred = blur.apply(&scene.pixels);
    let mut p = Vec::new();
    for q in [10.0, 90.0] {
        let mut raw = blurred.clone();
        add_noise(&mut raw, &NoiseModel { q, sigma: 2.0, full_scale: FULL_SCALE_14BIT }, &mut Rng::new(1));
        p.push(psnr(&blurred, &raw));
    }
    println!("noise PSNR: q=10 {:.2} dB, q=90 {:.2} dB", p[0], p[1]);
    assert!(p[0] > p[1] + 15.0, "{p:?}");
    // Seams would show as jumps at region borders on a smooth ramp.
    let ramp: Vec<f32> = (0..h * w).map(|i| (i % w) as f32 / w as f32 * 0.5 + 0.2).collect();
    let out = blur.apply(&ramp);
    for y in 40..h - 40 {
        for x in 40..w - 41 {
            let step = out[y * w + x + 1] - out[y * w + x];
            assert!((step - 0.5 / w as f32).abs() < 1e-4, "jump {step} at ({x}, {y})");
        }
    }
}

#[test]
fn blur_map_upsample_matches_ort_resize() {
    let map: Vec<f32> = (0..48).map(|i| ((i * 37) % 48) as f32 / 47.0).collect();
    for (oh, ow) in [(48, 64), (120, 160), (37, 53), (6, 8)] {
        let dims = |d: &[i64]| TensorShapeProto { dim: d.iter().map(|&v| Dimension { value: Some(DimensionValue::DimValue(v)), denotation: String::new() }).collect() };
        let vi = |n: &str, d: &[i64]| ValueInfoProto { name: n.into(), r#type: Some(TypeProto { value: Some(TypeValue::TensorType(TensorTypeProto { elem_type: 1, shape: Some(dims(d)) })), denotation: String::new() }), ..Default::default() };
        let s = |n: &str, v: &str| AttributeProto { name: n.into(), r#type: AttributeType::String as i32, s: Some(v.as_bytes().to_vec()), ..Default::default() };
        let sizes = pdi_compile::onnx::tensor_proto::from_tensor("sizes", &Tensor::new(vec![4], TensorData::I64(vec![1, 1, oh as i64, ow as i64])));
        let model = ModelProto {
            ir_version: 8,
            opset_import: vec![OperatorSetIdProto { domain: String::new(), version: 17 }],
            graph: Some(GraphProto {
                node: vec![NodeProto { op_type: "Resize".into(), input: vec!["k".into(), String::new(), String::new(), "sizes".into()], output: vec!["y".into()], attribute: vec![s("mode", "linear"), s("coordinate_transformation_mode", "half_pixel")], ..Default::default() }],
                input: vec![vi("k", &[1, 1, 6, 8])],
                output: vec![vi("y", &[1, 1, oh as i64, ow as i64])],
                initializer: vec![sizes],
                ..Default::default()
            }),
            ..Default::default()
        };
        let inputs = vec![("k".to_string(), Tensor::f32(vec![1, 1, 6, 8], map.clone()))];
        let ort = runtime::load(Engine::Ort, &model, &inputs, 1).unwrap().run(&inputs).unwrap().remove(0).1;
        let ours = resize_half_pixel(&map, 6, 8, oh, ow);
        let worst = ort.as_f32().unwrap().iter().zip(&ours).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(worst <= 1e-6, "{oh}x{ow}: max abs {worst}");
    }
}

#[test]
fn synthetic_scenes_are_deterministic_and_labelled() {
    let (a, b, c) = (synth::scene(320, 240, 5), synth::scene(320, 240, 5), synth::scene(320, 240, 6));
    assert_eq!(a.pixels, b.pixels);
    assert_eq!(a.labels, b.labels);
    assert_ne!(a.pixels, c.pixels);
    let total: usize = (0..20).map(|s| synth::scene(320, 240, s).labels.len()).sum();
    assert!(total >= 40, "{total} labels in 20 scenes");
    for s in 0..20 {
        for t in synth::scene(320, 240, s).labels {
            assert!(t.class < 6 && t.bbox[0] >= 0.0 && t.bbox[2] <= 320.0 && t.bbox[1] >= 0.0 && t.bbox[3] <= 240.0 && t.bbox[2] > t.bbox[0], "{t:?}");
        }
    }
}

#[test]
fn coco_folder_is_rescaled_with_its_boxes() {
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("flir");
    std::fs::create_dir(&src).unwrap();
    let img: Vec<f32> = (0..1024 * 768).map(|i| (i % 1024) as f32 / 1024.0).collect();
    pdi_compile::frames::write_gray16(&src.join("a.png"), 1024, 768, &img).unwrap();
    let coco = serde_json::json!({
        "images": [{"id": 7, "file_name": "data/a.png", "width": 1024, "height": 768}],
        "categories": [{"id": 1, "name": "person"}, {"id": 3, "name": "car"}, {"id": 9, "name": "dog"}],
        "annotations": [
            {"id": 1, "image_id": 7, "category_id": 1, "bbox": [100.0, 200.0, 50.0, 120.0]},
            {"id": 2, "image_id": 7, "category_id": 9, "bbox": [0.0, 0.0, 10.0, 10.0]},
            {"id": 3, "image_id": 7, "category_id": 3, "bbox": [512.0, 384.0, 256.0, 128.0]}
        ]
    });
    std::fs::write(dir.path().join("coco.json"), coco.to_string()).unwrap();
    let out = dir.path().join("out");
    let n = pdi_compile::dataset::import_folder(&src, &out, 640, 480, Some(&dir.path().join("coco.json"))).unwrap();
    assert_eq!(n, 2, "the dog is not an M3FD class");
    let labels = pdi_compile::frames::read_yolo_labels(&out.join("000000.txt"), 640.0, 480.0).unwrap().unwrap();
    assert_eq!(labels[0].class, 0);
    let b = labels[0].bbox;
    for (got, want) in b.iter().zip([62.5, 125.0, 93.75, 200.0]) {
        assert!((got - want).abs() < 1e-3, "{b:?}");
    }
    let (w, h, px) = pdi_compile::frames::read_gray(&out.join("000000.png")).unwrap();
    assert_eq!((w, h), (640, 480));
    assert!((px[240 * 640 + 320] - 0.5).abs() < 0.01, "area resampling keeps the ramp: {}", px[240 * 640 + 320]);
}

#[test]
fn committed_blur_maps_are_current() {
    for (lens, map) in [("calib/lens_single_lwir.yaml", "calib/single_lwir_blur.npy"), ("calib/lens_multi_lwir.yaml", "calib/multi_lwir_blur.npy")] {
        let lens = Lens::load(&repo().join(lens)).unwrap();
        let (_, kernels) = simulate(&lens, 6, 8, 31);
        let fresh = blur_map(&kernels.iter().map(|k| spot_stats(k, 31)).collect::<Vec<_>>(), 6, 8);
        let committed = pdi_compile::optics::blur_map::BlurMap::load(&repo().join(map)).unwrap();
        let worst = fresh.values.iter().zip(&committed.values).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(worst < 1e-4, "{map} is stale (max diff {worst}); regenerate it as calib/README.md says");
    }
}
