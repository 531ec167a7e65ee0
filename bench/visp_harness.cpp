// ViSP's model-based tracker (vpMbGenericTracker) over a recorded sequence, timed per frame.
//
// Built by bench/vs_visp.py with g++ and `pkg-config visp`. Reads a job file:
//
//   mode edges|klt          (klt: edges and KLT points together)
//   scanline 0|1            (scanline visibility test: non-convex parts)
//   model <file.cao>
//   frames <N>
//   camera <name> <config.xml> <image-list file> <16 numbers: T_camref_cam, row-major>
//   ...                     (one line per camera; the first is the reference)
//   pose <16 numbers: cMo of the reference camera at frame 0, row-major>
//
// and writes one line per frame: "<wall ms> <thread CPU ms> <16 numbers of cMo>" (the time of
// vpMbGenericTracker::track alone, images being read before the clock starts; the reference
// camera's pose of the object after tracking that frame). Frame 0 is the start: times 0.

#include <chrono>
#include <ctime>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include <visp3/core/vpHomogeneousMatrix.h>
#include <visp3/core/vpImage.h>
#include <visp3/io/vpImageIo.h>
#include <visp3/mbt/vpMbGenericTracker.h>

static double thread_cpu_ms() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}

static vpHomogeneousMatrix read_matrix(std::istream &in) {
  vpHomogeneousMatrix M;
  for (int i = 0; i < 4; i++)
    for (int j = 0; j < 4; j++) in >> M[i][j];
  return M;
}

int main(int argc, char **argv) {
  if (argc != 3) {
    std::cerr << "usage: visp_harness JOB OUT" << std::endl;
    return 2;
  }
  std::ifstream job(argv[1]);
  std::string key, mode = "edges", model;
  bool scanline = false;
  int frames = 0;
  std::vector<std::string> names, xmls;
  std::vector<std::vector<std::string> > images;
  std::vector<vpHomogeneousMatrix> c_ref;  // T_cam_camref per camera
  vpHomogeneousMatrix cMo;
  while (job >> key) {
    if (key == "mode") job >> mode;
    else if (key == "scanline") { int s; job >> s; scanline = s != 0; }
    else if (key == "model") job >> model;
    else if (key == "frames") job >> frames;
    else if (key == "camera") {
      std::string name, xml, list;
      job >> name >> xml >> list;
      vpHomogeneousMatrix refMc = read_matrix(job);
      names.push_back(name);
      xmls.push_back(xml);
      c_ref.push_back(refMc.inverse());
      std::ifstream lf(list);
      std::vector<std::string> paths;
      std::string p;
      while (std::getline(lf, p))
        if (!p.empty()) paths.push_back(p);
      images.push_back(paths);
    } else if (key == "pose") cMo = read_matrix(job);
    else { std::cerr << "visp_harness: unknown key " << key << std::endl; return 2; }
  }
  const size_t nc = names.size();
  if (nc == 0 || frames <= 0) { std::cerr << "visp_harness: no camera or no frames" << std::endl; return 2; }
  int type = vpMbGenericTracker::EDGE_TRACKER;
  if (mode == "klt") type |= vpMbGenericTracker::KLT_TRACKER;
  vpMbGenericTracker tracker(std::vector<int>(nc, type));
  // The generic tracker names its cameras Camera1, Camera2, ... (Camera for one).
  std::vector<std::string> tn;
  if (nc == 1) tn.push_back("Camera");
  else for (size_t k = 0; k < nc; k++) tn.push_back("Camera" + std::to_string(k + 1));
  std::map<std::string, std::string> cfg;
  std::map<std::string, vpHomogeneousMatrix> cMc;
  for (size_t k = 0; k < nc; k++) { cfg[tn[k]] = xmls[k]; cMc[tn[k]] = c_ref[k]; }
  if (nc == 1) tracker.loadConfigFile(xmls[0]);
  else tracker.loadConfigFile(cfg);
  tracker.loadModel(model);
  if (nc > 1) tracker.setCameraTransformationMatrix(cMc);
  tracker.setScanLineVisibilityTest(scanline);
  tracker.setDisplayFeatures(false);

  std::vector<vpImage<unsigned char> > I(nc);
  std::map<std::string, const vpImage<unsigned char> *> mI;
  std::map<std::string, vpHomogeneousMatrix> mPose;
  std::ofstream out(argv[2]);
  int failures = 0;  // frames whose tracking threw (the first is reported)
  for (int f = 0; f < frames; f++) {
    for (size_t k = 0; k < nc; k++) {
      vpImageIo::read(I[k], images[k][f]);
      mI[tn[k]] = &I[k];
    }
    double ms = 0.0, cpu_ms = 0.0;
    if (f == 0) {
      if (nc == 1) tracker.initFromPose(I[0], cMo);
      else {
        for (size_t k = 0; k < nc; k++) mPose[tn[k]] = c_ref[k] * cMo;
        tracker.initFromPose(mI, mPose);
      }
    } else {
      auto t0 = std::chrono::steady_clock::now();
      double c0 = thread_cpu_ms();
      try {
        if (nc == 1) tracker.track(I[0]);
        else tracker.track(mI);
      } catch (const vpException &e) {
        if (failures++ == 0) std::cerr << "visp_harness: frame " << f << ": " << e.getMessage() << std::endl;
      }
      cpu_ms = thread_cpu_ms() - c0;
      ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    }
    tracker.getPose(cMo);
    out << ms << " " << cpu_ms;
    for (int i = 0; i < 4; i++)
      for (int j = 0; j < 4; j++) out << " " << cMo[i][j];
    out << "\n";
  }
  if (failures) std::cerr << "visp_harness: " << failures << " frames failed" << std::endl;
  return 0;
}
