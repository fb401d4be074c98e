//! What requests mean, tested in-process: the core (`c4g-service`) over a real model (c4g-tiny on
//! ONNX Runtime) and a real store in a temporary directory, with no port and no transport. The
//! end-to-end tests (`tests/e2e`) hold the processes and the wire; these hold the layers: one clip
//! uploaded once, its sets from the one set source whichever way they are asked for, its views
//! rendered from those sets, and a deleted clip gone from every layer.
//!
//! Sets and images are compared exactly (`==`): every path below runs the same engine and
//! rasterizer on the same inputs on this machine, so any difference is a behaviour, not rounding.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::PathBuf;
use std::sync::Arc;

use bytes::Bytes;
use c4g_engine::Engine;
use c4g_service::clips::intake::{IntakeOptions, Media};
use c4g_service::config::Config;
use c4g_service::sets::quality::QualitySpec;
use c4g_service::sets::streaming::{self, Spacing, StreamRequest};
use c4g_service::views::camera::CameraSpec;
use c4g_service::views::render::{PathRequest, ViewRequest};
use c4g_service::{Service, ServiceErrorKind};
use clap::Parser;

/// Outside CI a missing ONNX Runtime skips a test with a message; in CI it fails, so a
/// misconfigured CI cannot pass by running nothing.
fn ready() -> bool {
    if std::env::var_os("ORT_DYLIB_PATH").is_some_and(|p| !p.is_empty()) {
        return true;
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "in CI every core test must run: ORT_DYLIB_PATH is not set"
    );
    eprintln!("skipped: ORT_DYLIB_PATH is not set (scripts/env.sh sets it)");
    false
}

/// The service over c4g-tiny and a fresh store; the store lives as long as the guard.
fn service() -> (Arc<Service>, tempfile::TempDir) {
    let model = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../models/c4g-tiny");
    let store = tempfile::tempdir().unwrap();
    let config = Config::parse_from([
        "c4g-server",
        "--model",
        model.to_str().unwrap(),
        "--store-dir",
        store.path().to_str().unwrap(),
        "--renderer",
        "cpu",
    ]);
    let engine = Engine::load(&config.model, config.engine_options()).unwrap();
    (Arc::new(Service::new(engine, &config).unwrap()), store)
}

/// Four frames of a small moving pattern, as PNG.
fn frames() -> Vec<Bytes> {
    (0..4u32)
        .map(|k| {
            let image = image::RgbImage::from_fn(48, 48, |x, y| {
                let v = ((x + 3 * k) * 5 % 256) as u8;
                image::Rgb([v, (y * 5 % 256) as u8, 255 - v])
            });
            let mut png = Vec::new();
            image
                .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
                .unwrap();
            Bytes::from(png)
        })
        .collect()
}

/// Uploads the four frames, timed 0.1 s apart.
async fn upload(service: &Arc<Service>) -> (String, (f64, f64), bool) {
    let (record, created) = service
        .upload(Media::Frames(frames()), IntakeOptions::default())
        .await
        .unwrap();
    (record.id.clone(), record.span(), created)
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}

#[test]
fn the_same_upload_is_the_same_clip_and_is_encoded_once() {
    if !ready() {
        return;
    }
    let (service, _store) = service();
    runtime().block_on(async {
        let (first, span, created) = upload(&service).await;
        assert!(created);
        assert!(span.1 > span.0, "four timed frames span time: {span:?}");
        let (again, _, created) = upload(&service).await;
        assert_eq!(again, first);
        assert!(
            !created,
            "the second upload of the same bytes finds the clip"
        );
    });
}

#[test]
fn sets_are_the_same_however_they_are_asked_for() {
    if !ready() {
        return;
    }
    let (service, _store) = service();
    runtime().block_on(async {
        let (id, (first, last), _) = upload(&service).await;
        let times = vec![first, (first + last) / 2.0, last];
        let decoded = service
            .sets
            .decode(&id, times.clone(), QualitySpec::default())
            .await
            .unwrap();
        assert_eq!(
            decoded.iter().map(|(t, _)| *t).collect::<Vec<_>>(),
            times,
            "one set per asked time, in order"
        );
        // Two requests at once share one batched decoder run: each gets its own sets back,
        // the same as a decode of its times alone.
        let (a, b) = tokio::join!(
            service
                .sets
                .decode(&id, vec![times[0]], QualitySpec::default()),
            service
                .sets
                .decode(&id, vec![times[2], times[1]], QualitySpec::default()),
        );
        assert_eq!(a.unwrap(), vec![decoded[0].clone()]);
        assert_eq!(b.unwrap(), vec![decoded[2].clone(), decoded[1].clone()]);
        // A stream of the same times serves the same sets.
        let request = StreamRequest {
            start: Some(first),
            end: Some(last),
            spacing: Spacing::Step((last - first) / 2.0),
            quality: QualitySpec::default(),
        };
        let mut stream = streaming::stream(&service.sets, &id, &request)
            .await
            .unwrap();
        assert_eq!(stream.times, times);
        let mut streamed = Vec::new();
        while let Some(set) = stream.sets.recv().await {
            streamed.push(set.unwrap());
        }
        assert_eq!(streamed, decoded);
    });
}

#[test]
fn a_time_outside_the_clip_is_refused_before_any_work() {
    if !ready() {
        return;
    }
    let (service, _store) = service();
    runtime().block_on(async {
        let (id, (_, last), _) = upload(&service).await;
        let error = service
            .sets
            .decode(&id, vec![last + 1.0], QualitySpec::default())
            .await
            .unwrap_err();
        assert_eq!(error.kind(), ServiceErrorKind::InvalidInput);
        assert!(
            error
                .to_string()
                .contains("outside the clip's context span"),
            "{error}"
        );
    });
}

#[test]
fn a_view_and_every_frame_of_a_path_render_the_sets_the_set_source_gives() {
    if !ready() {
        return;
    }
    let (service, _store) = service();
    runtime().block_on(async {
        let (id, (first, last), _) = upload(&service).await;
        let view = ViewRequest {
            t: first,
            camera: CameraSpec::default(),
            width: Some(40),
            height: Some(30),
            background: [0.2, 0.3, 0.4],
        };
        let image = service
            .views
            .render_view(&id, view.clone(), QualitySpec::default())
            .await
            .unwrap();
        let record = service.store.get(&id).unwrap();
        let camera = service.views.view_camera(&record, &view).unwrap();
        let set = service
            .sets
            .decode(&id, vec![first], QualitySpec::default())
            .await
            .unwrap()
            .remove(0)
            .1;
        let expected = service
            .views
            .render_now(&set, &camera, view.background)
            .unwrap();
        assert_eq!(image, expected);

        // The one trajectory render: five frames from start to end, in time order, each the
        // render of the set at its time from its planned camera.
        let path = PathRequest {
            frames: Some(5),
            width: Some(24),
            height: Some(24),
            ..PathRequest::default()
        };
        let rendered = service
            .views
            .render_path_all(&id, &path, &QualitySpec::default(), |t, image| {
                Ok((t, image))
            })
            .await
            .unwrap();
        let plan = service.views.plan_path(&record, &path).unwrap();
        assert_eq!(rendered.len(), 5);
        assert_eq!(rendered[0].0, first);
        assert_eq!(rendered[4].0, last);
        let times: Vec<f64> = plan.iter().map(|(t, _)| *t).collect();
        let sets = service
            .sets
            .decode(&id, times, QualitySpec::default())
            .await
            .unwrap();
        for ((t, image), ((_, set), (planned, camera))) in
            rendered.iter().zip(sets.iter().zip(&plan))
        {
            assert_eq!(t, planned);
            assert_eq!(
                image,
                &service.views.render_now(set, camera, [0.0; 3]).unwrap()
            );
        }
    });
}

#[test]
fn a_deleted_clip_is_gone_from_every_layer() {
    if !ready() {
        return;
    }
    let (service, _store) = service();
    runtime().block_on(async {
        let (id, (first, _), _) = upload(&service).await;
        service.delete(&id).await.unwrap();
        let decode = service
            .sets
            .decode(&id, vec![first], QualitySpec::default())
            .await
            .unwrap_err();
        assert_eq!(decode.kind(), ServiceErrorKind::NotFound);
        let view = ViewRequest {
            t: first,
            camera: CameraSpec::default(),
            width: None,
            height: None,
            background: [0.0; 3],
        };
        let render = service
            .views
            .render_view(&id, view, QualitySpec::default())
            .await
            .unwrap_err();
        assert_eq!(render.kind(), ServiceErrorKind::NotFound);
        let frame = service.store.context_frame_png(&id, 0).await.unwrap_err();
        assert_eq!(frame.kind(), ServiceErrorKind::NotFound);
    });
}

#[test]
fn a_request_that_races_a_delete_is_served_or_not_found_and_writes_nothing_back() {
    if !ready() {
        return;
    }
    use c4g_service::views::recovery::RecoverOptions;
    let (service, _store) = service();
    runtime().block_on(async {
        // The delete lands before, during and after the recovery's reads and its write.
        for delay_ms in [0, 5, 20, 80, 300] {
            let (id, _, _) = upload(&service).await;
            let recovering = {
                let (service, id) = (service.clone(), id.clone());
                tokio::spawn(async move {
                    service
                        .views
                        .recover_cameras(&id, RecoverOptions::default())
                        .await
                })
            };
            let framing = {
                let (service, id) = (service.clone(), id.clone());
                tokio::spawn(async move { service.store.context_frame_png(&id, 3).await })
            };
            tokio::time::sleep(std::time::Duration::from_millis(delay_ms)).await;
            service.delete(&id).await.unwrap();
            let recovered = recovering.await.unwrap();
            if let Err(e) = &recovered {
                assert_eq!(e.kind(), ServiceErrorKind::NotFound, "{delay_ms} ms: {e}");
            }
            if let Err(e) = framing.await.unwrap() {
                assert_eq!(e.kind(), ServiceErrorKind::NotFound, "{delay_ms} ms: {e}");
            }
            let place = service.store.clip_file(&id, "recovered-cameras.json");
            assert!(
                !place.exists(),
                "{delay_ms} ms: written into a deleted clip's place"
            );
            assert!(!place.parent().unwrap().exists(), "{delay_ms} ms");
        }
    });
}
