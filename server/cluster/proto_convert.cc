#include "server/cluster/proto_convert.h"

namespace oxbow::cluster {

std::vector<sift::Keypoint> KeypointsFrom(const google::protobuf::RepeatedField<float>& values) {
  std::vector<sift::Keypoint> out(static_cast<size_t>(values.size() / kKeypointValues));
  for (size_t i = 0; i < out.size(); ++i) {
    const float* v = values.data() + i * kKeypointValues;
    out[i].x = v[0];
    out[i].y = v[1];
    out[i].scale = v[2];
    out[i].orientation = v[3];
  }
  return out;
}

void PutKeypoints(std::span<const sift::Keypoint> keypoints, google::protobuf::RepeatedField<float>* out) {
  out->Resize(static_cast<int>(keypoints.size()) * kKeypointValues, 0.0f);
  float* v = out->mutable_data();
  for (const sift::Keypoint& k : keypoints) {
    *v++ = k.x;
    *v++ = k.y;
    *v++ = k.scale;
    *v++ = k.orientation;
  }
}

std::vector<index::QueryTerm> TermsFrom(const google::protobuf::RepeatedPtrField<Term>& terms) {
  std::vector<index::QueryTerm> out;
  out.reserve(static_cast<size_t>(terms.size()));
  for (const Term& t : terms) out.push_back({t.word(), t.weight()});
  return out;
}

void PutTerms(std::span<const index::QueryTerm> terms, google::protobuf::RepeatedPtrField<Term>* out) {
  for (const index::QueryTerm& t : terms) {
    Term* term = out->Add();
    term->set_word(t.word);
    term->set_weight(t.weight);
  }
}

index::ImageRecord FromProto(const Record& r) {
  return {.id = r.id(), .source_path = r.source_path(), .width = r.width(), .height = r.height(),
          .num_features = r.num_features(), .metadata_json = r.metadata_json(), .added_unix_ms = r.added_unix_ms()};
}

void PutRecord(const index::ImageRecord& record, Record* out) {
  out->set_id(record.id);
  out->set_width(record.width);
  out->set_height(record.height);
  out->set_num_features(record.num_features);
  out->set_metadata_json(record.metadata_json);
  out->set_source_path(record.source_path);
  out->set_added_unix_ms(record.added_unix_ms);
}

}  // namespace oxbow::cluster
